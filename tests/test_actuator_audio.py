"""Audio-path actuators: the wav writer (deterministic timeline), the PortAudio actuator on an
ALSA file plugin (waveform content) and on a JACK dummy server (real-time pacing, underruns,
the watchdog in the callback).

PortAudio reads the ALSA configuration and the JACK server name once, when it initializes
(at ``import sounddevice``), so those tests run the actuator in a child Python with HOME /
JACK_DEFAULT_SERVER set; the child reports JSON and the raw samples, the test checks them.
"""

from __future__ import annotations

import ctypes.util
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import uuid

import numpy as np
import pytest

from burrforce.server.devices.actuators.synth import Perceptual
from burrforce.server.devices.actuators.wav import WavActuator, read_wav

RATE = 48_000
MS = 1_000_000


def _peak(x: np.ndarray, rate: int = RATE) -> tuple[float, float]:
    """(Hz of the largest Hann-windowed rfft bin, the sine amplitude there)."""
    window = np.hanning(x.size)
    spectrum = np.abs(np.fft.rfft(x * window))
    k = int(np.argmax(spectrum))
    return k * rate / x.size, 2 * spectrum[k] / window.sum()


def _max_step_bound(hz: float, level: float, ramp_frames: int) -> float:
    return 2 * math.pi * hz / RATE * level + level / (ramp_frames - 1) + 1e-4


# -- the wav writer ----------------------------------------------------------------------------
def _stream(wav: WavActuator, amplitude_N: float, hz: float, start_ms: int, stop_ms: int) -> None:
    for ms in range(start_ms, stop_ms):
        wav.update(amplitude_N, hz, ms * MS)


@pytest.mark.parametrize("sample_format", ["int16", "float32"])
def test_wav_tone_frequency_amplitude_and_watchdog(tmp_path, sample_format):
    path = tmp_path / "cue.wav"
    with WavActuator(path, sample_format=sample_format, full_scale_N=2.0) as wav:
        _stream(wav, 1.0, 300.0, 0, 1000)  # 1 s of 1 N → level 0.5, updates at 1 kHz
        wav.advance(1300 * MS)  # the stream stopped at 999 ms
    rate, x = read_wav(path)
    assert rate == RATE
    peak_hz, amplitude = _peak(x[48:48_048])
    assert abs(peak_hz - 300.0) <= 1.0
    assert amplitude == pytest.approx(0.5, rel=0.16)
    assert np.max(np.abs(x[48:48_000])) == pytest.approx(0.5, abs=1e-3)
    # silent by last update + 50 ms, on the file's own timeline
    last_sound = int(np.nonzero(x)[0][-1])
    assert last_sound / RATE * 1e9 <= 999 * MS + 50 * MS
    assert wav.stats.watchdog_silences == 1
    assert wav.stats.watchdog_silent_ns <= 1049 * MS
    assert x.size == 1300 * 48
    assert np.max(np.abs(np.diff(x))) <= _max_step_bound(300.0, 0.5, 48) + 2 / 32767


def test_wav_is_deterministic_and_follows_parameter_changes(tmp_path):
    files = []
    for name in ("a.wav", "b.wav"):
        with WavActuator(tmp_path / name, perceptual=Perceptual("clamp")) as wav:
            _stream(wav, 0.4, 200.0, 0, 500)
            _stream(wav, 0.8, 1000.0, 500, 1000)  # clamped to the 800 Hz corner
        files.append((tmp_path / name).read_bytes())
    assert files[0] == files[1]
    _, x = read_wav(tmp_path / "a.wav")
    assert abs(_peak(x[4800:4800 + 19_200])[0] - 200.0) <= 2.5
    assert abs(_peak(x[28_800:28_800 + 19_200])[0] - 800.0) <= 2.5
    assert np.max(np.abs(x[28_800:48_000])) == pytest.approx(0.8, abs=1e-3)
    # close ramps down: the file ends silent, without a click
    assert x[-1] == 0.0
    assert np.max(np.abs(np.diff(x))) <= _max_step_bound(800.0, 0.8, 48) + 2 / 32767


def test_wav_rejects_time_going_backwards_and_bad_values(tmp_path):
    with WavActuator(tmp_path / "x.wav") as wav:
        wav.update(0.5, 100.0, 10 * MS)
        with pytest.raises(ValueError, match="backwards"):
            wav.update(0.5, 100.0, 5 * MS)
        with pytest.raises(ValueError, match="amplitude"):
            wav.update(math.nan, 100.0, 20 * MS)
        with pytest.raises(ValueError, match="frequency"):
            wav.update(0.5, -3.0, 20 * MS)
    with pytest.raises(RuntimeError, match="not open"):
        wav.update(0.5, 100.0, 30 * MS)
    with pytest.raises(ValueError, match="sample_format"):
        WavActuator(tmp_path / "y.wav", sample_format="mp3")


def test_wav_bad_value_silences(tmp_path):
    path = tmp_path / "x.wav"
    with WavActuator(path) as wav:
        _stream(wav, 0.5, 250.0, 0, 20)
        with pytest.raises(ValueError):
            wav.update(math.inf, 250.0, 20 * MS)
        wav.advance(30 * MS)
    _, x = read_wav(path)
    assert np.any(x[:19 * 48])
    assert not np.any(x[21 * 48:])  # the ramp block after 20 ms, then nothing


# -- PortAudio ---------------------------------------------------------------------------------
def _portaudio_missing() -> str | None:
    if ctypes.util.find_library("portaudio") is None:
        return "PortAudio is not installed (apt-get install libportaudio2)"
    try:
        import sounddevice  # noqa: F401
    except (ImportError, OSError) as exc:
        return f"sounddevice unusable: {exc}"
    return None


def _run_child(script: str, env: dict[str, str], timeout_s: float = 60.0) -> dict:
    full_env = {**os.environ, **env}
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], env=full_env,
                          capture_output=True, text=True, timeout=timeout_s)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


ALSA_CHILD = """
    import json, sys, time
    from burrforce.server.devices.actuators.audio import AudioActuator
    out = {}
    act = AudioActuator("burrfile", blocksize=64, full_scale_N=1.0)
    deadline = time.monotonic() + 30.0
    with act:
        while act.callbacks < 20 and time.monotonic() < deadline:
            time.sleep(0.001)
        out["blocks_before"] = act.callbacks
        # The file plugin is not paced: count blocks, not seconds.
        act.update(0.5, 300.0)
        start = act.callbacks
        while act.callbacks - start < 1600 and time.monotonic() < deadline:
            act.update(0.5, 300.0)
            time.sleep(0.001)
        out["blocks_toned"] = act.callbacks - start
        while not act.stats.watchdog_silences and time.monotonic() < deadline:
            time.sleep(0.005)  # the stream stalls: the callback's watchdog must act
        stop = act.callbacks
        while act.callbacks - stop < 200 and time.monotonic() < deadline:
            time.sleep(0.001)
    out.update(watchdog=act.stats.watchdog_silences, error=repr(act.callback_error),
               callbacks=act.callbacks, underruns=act.underruns)
    print(json.dumps(out))
"""


def test_audio_alsa_file_plugin_content_and_stall(tmp_path):
    reason = _portaudio_missing()
    if reason:
        pytest.skip(reason)
    raw = tmp_path / "out.raw"
    (tmp_path / ".asoundrc").write_text(
        "pcm.burrnull { type null }\n"
        f'pcm.burrfile {{ type file slave.pcm "burrnull" file "{raw}" format "raw" }}\n')
    env = {"HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path / ".config")}
    env.pop("ALSA_CONFIG_PATH", None)
    result = _run_child(ALSA_CHILD, env)
    assert result["error"] == "None"
    assert result["watchdog"] == 1
    assert result["blocks_toned"] >= 1600
    x = np.fromfile(raw, dtype=np.float32)  # mono float32, exactly what the callback wrote
    # what the callback wrote, plus the zeros PortAudio primes the ALSA buffer with
    assert 0 <= x.size - result["callbacks"] * 64 <= 16 * 64
    sounding = np.nonzero(x)[0]
    first, last = int(sounding[0]), int(sounding[-1])
    assert first >= result["blocks_before"] * 64  # silent until the first update
    tone = x[first + 64:first + 64 + 96_000]  # 2 s past the ramp-in block: 0.5 Hz bins
    peak_hz, amplitude = _peak(tone)
    assert abs(peak_hz - 300.0) <= 0.5
    assert np.max(np.abs(tone)) == pytest.approx(0.5, abs=1e-3)
    assert amplitude == pytest.approx(0.5, rel=0.16)
    # After the stall: a ramp, then silence to the end (≥ 200 blocks), never a click.
    assert x.size - last > 190 * 64
    assert np.max(np.abs(np.diff(x))) <= _max_step_bound(300.0, 0.5, 64)


def _jackd_missing() -> str | None:
    if shutil.which("jackd") is None:
        return "jackd is not installed (apt-get install jackd2)"
    return _portaudio_missing()


JACK_CHILD = """
    import json, sys, time
    import sounddevice as sd
    deadline = time.monotonic() + 20.0
    while True:  # the server may still be starting: re-scan until PortAudio sees JACK
        apis = [i for i, api in enumerate(sd.query_hostapis()) if "JACK" in api["name"]]
        if apis or time.monotonic() > deadline:
            break
        sd._terminate(); time.sleep(0.2); sd._initialize()
    if not apis:
        print(json.dumps({"skip": "PortAudio has no JACK host API"})); sys.exit(0)
    device = sd.query_hostapis(apis[0])["default_output_device"]
    from burrforce.server.devices.actuators.audio import AudioActuator
    out = {}
    act = AudioActuator(device, blocksize=64, full_scale_N=1.0)
    with act:
        out["latency_s"] = act.output_latency_s
        t0 = time.monotonic(); c0 = act.callbacks
        while time.monotonic() - t0 < 1.0:
            act.update(0.5, 250.0)
            time.sleep(0.001)
        out["callbacks_per_s"] = (act.callbacks - c0) / (time.monotonic() - t0)
        last = act.stats.last_update_ns
        while not act.stats.watchdog_silences and time.monotonic() - t0 < 3.0:
            time.sleep(0.002)
        out["silent_after_ms"] = (act.stats.watchdog_silent_ns - last) / 1e6
        # Starve the callback of the GIL for 0.3 s: the JACK server runs on, PortAudio must
        # report the missed cycles as output underflow.
        act.update(0.5, 250.0)
        u0 = act.underruns
        sys.setswitchinterval(0.3)
        t1 = time.monotonic()
        while time.monotonic() - t1 < 0.3:
            pass
        sys.setswitchinterval(0.005)
        time.sleep(0.2)
        out["underruns_starved"] = act.underruns - u0
    out.update(underruns=act.underruns, error=repr(act.callback_error))
    print(json.dumps(out))
"""


@pytest.fixture
def jack_server():
    reason = _jackd_missing()
    if reason:
        pytest.skip(reason)
    name = f"burrtest-{uuid.uuid4().hex[:8]}"
    env = {**os.environ, "JACK_NO_AUDIO_RESERVATION": "1", "JACK_NO_START_SERVER": "1"}
    proc = subprocess.Popen(
        ["jackd", "-n", name, "--no-realtime", "-d", "dummy", "-r", str(RATE), "-p", "64"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    time.sleep(0.3)
    if proc.poll() is not None:
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        pytest.skip(f"jackd did not start: {out[-500:]}")
    try:
        yield name
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_audio_jack_callback_keeps_up_and_watchdog(jack_server):
    result = _run_child(JACK_CHILD, {"JACK_DEFAULT_SERVER": jack_server,
                                     "JACK_NO_START_SERVER": "1"})
    if "skip" in result:
        pytest.skip(result["skip"])
    print(result)
    assert result["error"] == "None"
    # 48 000 / 64 = 750 callbacks per second on the dummy server's clock
    assert 0.7 * 750 <= result["callbacks_per_s"] <= 1.3 * 750
    # the callback's watchdog: silent within 50 ms of the last update (+ a generous 10 ms
    # for a late callback on a loaded machine)
    assert 0 < result["silent_after_ms"] <= 60.0
    assert result["underruns_starved"] >= 1


def test_audio_missing_device_is_a_clear_error(tmp_path):
    reason = _portaudio_missing()
    if reason:
        pytest.skip(reason)
    script = """
        import json
        from burrforce.server.devices.base import DeviceNotFound
        from burrforce.server.devices.actuators.audio import AudioActuator
        try:
            AudioActuator("no-such-card-xyz").open()
            print(json.dumps({"raised": None}))
        except DeviceNotFound as exc:
            print(json.dumps({"raised": str(exc)}))
    """
    result = _run_child(script, {"HOME": str(tmp_path)})
    assert result["raised"] and "no-such-card-xyz" in result["raised"]


def test_audio_missing_portaudio_says_what_to_install(tmp_path):
    """Without libportaudio, sounddevice raises OSError at import: we name the package."""
    script = """
        import json, ctypes.util
        ctypes.util.find_library = lambda name: None  # as on a machine without PortAudio
        from burrforce.server.devices.base import VendorLibraryMissing
        from burrforce.server.devices.actuators.audio import AudioActuator
        try:
            AudioActuator().open()
            print(json.dumps({"raised": None}))
        except VendorLibraryMissing as exc:
            print(json.dumps({"raised": str(exc)}))
    """
    result = _run_child(script, {"HOME": str(tmp_path)})
    if result["raised"] is None:
        pytest.skip("this sounddevice finds PortAudio without ctypes.util (allowed in CI)")
    assert "apt-get install libportaudio2" in result["raised"]


def test_audio_rejects_bad_configuration():
    from burrforce.server.devices.actuators.audio import AudioActuator

    with pytest.raises(ValueError, match="blocksize"):
        AudioActuator(blocksize=2)
    with pytest.raises(ValueError, match="channel"):
        AudioActuator(channel=2, channels=2)
    with pytest.raises(ValueError, match="watchdog"):
        AudioActuator(watchdog_ms=0.0)
