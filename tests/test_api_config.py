"""serve's configuration: defaults ← TOML ← environment ← flags, and clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from burrforce.server.api.config import ServeConfig, load_config


def test_precedence_file_environment_flags(tmp_path):
    toml = tmp_path / "burrforce.toml"
    toml.write_text('[server]\nhttp_port = 9000\nudp_port = 9001\ncors_origins = ["http://a"]\n'
                    'data_dir = "~/bf"\n[session]\nframe = "unity"\nvoxel_mm = 0.1\n')
    config = load_config(toml, {"udp_port": 5, "host": None},
                         {"BURRFORCE_HTTP_PORT": "9100", "BURRFORCE_MAX_SESSIONS": "3",
                          "BURRFORCE_NO_AUTH": "yes"})
    assert (config.http_port, config.udp_port, config.max_sessions) == (9100, 5, 3)
    assert config.frame == "unity" and config.voxel_mm == 0.1 and config.no_auth is True
    assert config.cors_origins == ("http://a",) and config.host == "127.0.0.1"
    assert config.data_dir == Path("~/bf").expanduser()
    assert load_config(None, None, {}) == ServeConfig()


@pytest.mark.parametrize(("text", "env", "words"), [
    ("[server]\nbogus = 1\n", {}, "unknown key 'bogus'"),
    ("[nope]\nx = 1\n", {}, "unknown table [nope]"),
    ("[server]\nhttp_port = 'x'\n", {}, "http_port has the wrong type"),
    ("[server]\nhttp_port = 70000\n", {}, "port number"),
    ("[server\n", {}, "not valid TOML"),
    ("", {"BURRFORCE_UDP_PORT": "abc"}, "BURRFORCE_UDP_PORT"),
    ("", {"BURRFORCE_TOKEN": "short"}, "at least 16"),
    ("", {"BURRFORCE_MAX_SESSIONS": "0"}, "max_sessions"),
    ("[server]\nwake_ahead_us = -5\n", {}, "wake-ahead lead must be within [0, 5000] µs"),
    ("", {"BURRFORCE_WAKE_CPU_SHARE": "2"}, "CPU share must be within [0.01, 1]"),
    ("", {"BURRFORCE_WAKE_AHEAD_US": "soon"}, "wake_ahead_us has the wrong type"),
])
def test_bad_settings_say_what_is_wrong(tmp_path, text, env, words):
    toml = tmp_path / "c.toml"
    toml.write_text(text)
    with pytest.raises(ValueError, match=None) as err:
        load_config(toml, None, env)
    assert words in str(err.value)


def test_waking_ahead_from_file_environment_and_flags(tmp_path):
    """The hot loops' waking ahead (``hotloop.wake``) is set like the rest; 0 turns it off."""
    toml = tmp_path / "c.toml"
    toml.write_text("[server]\nwake_ahead_us = 200\nwake_cpu_share = 0.3\n")
    config = load_config(toml, None, {})
    assert (config.wake.lead_us, config.wake.cpu_share, config.wake.enabled) == (200, 0.3, True)
    config = load_config(toml, {"wake_ahead_us": 0.0}, {"BURRFORCE_WAKE_CPU_SHARE": "0.5"})
    assert (config.wake.lead_us, config.wake.cpu_share, config.wake.enabled) == (0, 0.5, False)
    assert ServeConfig().wake.enabled


def test_realtime_from_file_environment_and_flags(tmp_path):
    """``serve --realtime`` (``server.realtime``) is off unless asked for."""
    assert ServeConfig().realtime is False
    toml = tmp_path / "c.toml"
    toml.write_text("[server]\nrealtime = true\n")
    assert load_config(toml, None, {}).realtime is True
    assert load_config(None, None, {"BURRFORCE_REALTIME": "yes"}).realtime is True
    assert load_config(toml, None, {"BURRFORCE_REALTIME": "0"}).realtime is False
    # The flag is store_true with default None: absent, it leaves the file's value.
    assert load_config(toml, {"realtime": None}, {}).realtime is True
    toml.write_text("[server]\nrealtime = \"sometimes\"\n")
    with pytest.raises(ValueError, match="realtime"):
        load_config(toml, None, {})


def test_a_missing_file_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="cannot read the config file"):
        load_config(tmp_path / "missing.toml")

