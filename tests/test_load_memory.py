"""Large and hostile bone files against ``burrforce serve`` as a client sends them: uploaded,
then a session created on each. The control plane's peak resident memory is measured per
file (the kernel's peak, reset before each): it never passes the load budget; a gzip bomb is
refused in under 2 s; a file too large for the budget is refused from its header.

The files are a few megabytes each, written a slab at a time (``bench.large_volumes``): this
test never holds more than one slab of them, and no load here holds more than ~1 GiB."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from burrforce.server.bench.large_volumes import SUFFIXES, write_bomb, write_ct
from burrforce.server.bench.load_files import load_file
from burrforce.server.bench.serve_process import spawn_serve
from burrforce.server.bone.loaders.budget import DEFAULT_WORK_BYTES, bone_bytes

MIB = 1 << 20
#: Growth of the control plane's memory a refused file may cause (the request, its answer).
REFUSED_GROWTH_BYTES = 64 * MIB


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("large")
    out = {}
    for fmt, suffix in SUFFIXES.items():
        out[f"ct512-{fmt}"] = write_ct(folder / f"ct512{suffix}", 512, fmt)
        out[f"ct1024-{fmt}"] = write_ct(folder / f"ct1024{suffix}", 1024, fmt)
        out[f"bomb-{fmt}"] = write_bomb(folder / f"bomb{suffix}", 1024, 8 << 30, fmt)
    return out


@contextmanager
def _serving(folder: Path, env: dict[str, str] | None = None) -> Iterator[tuple[httpx.Client,
                                                                               int]]:
    """A REST client of ``burrforce serve`` (the workpiece in session 1) and its pid; the
    server must stop cleanly."""
    serve = spawn_serve(folder, "--bone", "phantom:workpiece", env=env)
    c = serve.connection
    try:
        with httpx.Client(base_url=f"{c.http_url}/v1", timeout=300.0,
                          headers={"Authorization": f"Bearer {c.token}"}) as api:
            yield api, serve.proc.pid
    finally:
        code, out = serve.stop()
    assert code == 0, out


def test_default_budget_refuses_bombs_at_once_and_loads_a_float64_512_cube_within_it(
        files, tmp_path):
    assert all(f.stat().st_size < 16e6 for f in files.values())  # a few MB each
    with _serving(tmp_path) as (api, pid):
        for fmt in SUFFIXES:
            bomb = load_file(api, pid, files[f"bomb-{fmt}"], "density", 2)
            assert bomb["status"] == 422, bomb
            assert "inflates to 0 bytes" in bomb["detail"] and "refused before" in \
                bomb["detail"]
            assert bomb["load_s"] < 2.0, bomb
            assert bomb["peak_rss"] - bomb["rss_before"] < REFUSED_GROWTH_BYTES, bomb

            ct = load_file(api, pid, files[f"ct512-{fmt}"], "ct", 2)
            assert ct["status"] == 201, ct
            assert ct["shape"] == [512, 512, 512]
            budget = bone_bytes((512, 512, 512)) + DEFAULT_WORK_BYTES
            # The whole process, its 0.25 GB of interpreter and libraries included.
            assert ct["peak_rss"] <= budget, (ct, budget)
            print(f"{fmt}: bomb refused in {bomb['load_s']} s; 512³ float64 loaded in "
                  f"{ct['load_s']} s, peak RSS {ct['peak_rss'] / MIB:.0f} MiB (from "
                  f"{ct['rss_before'] / MIB:.0f}; budget {budget / MIB:.0f})",
                  file=sys.stderr)


def test_a_budget_refuses_a_float64_1024_cube_from_its_header(files, tmp_path):
    budget = 1 << 30
    with _serving(tmp_path, {"BURRFORCE_LOAD_BUDGET_BYTES": "1GiB"}) as (api, pid):
        for fmt in SUFFIXES:
            big = load_file(api, pid, files[f"ct1024-{fmt}"], "ct", 2)
            assert big["status"] == 413, big
            assert "more than the load budget of 1,024 MiB" in big["detail"], big
            assert "load_budget_bytes" in big["detail"]
            assert big["load_s"] < 2.0, big
            assert big["peak_rss"] - big["rss_before"] < REFUSED_GROWTH_BYTES, big
            assert big["peak_rss"] <= budget
        # The session the refused loads were for never existed; the server still serves.
        assert api.get("/sessions/2").status_code == 404
        assert api.get("/health").status_code == 200


def test_bench_loads_files_beside_a_streaming_session(files, tmp_path):
    """``bench load-while-streaming --file``: the rows it reports for a file."""
    import json
    import subprocess

    done = subprocess.run(
        [sys.executable, "-m", "burrforce.server.cli", "bench", "load-while-streaming",
         "--file", str(files["bomb-nrrd"]), "--quiet-s", "0.5", "--json",
         "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    (row,) = result["files"]
    assert row["status"] == 422 and row["name"] == "bomb.nrrd"
    assert row["peak_rss"] >= row["rss_before"] > 0
    assert row["samples"] > 0 and "lost" in row
    assert result["during_loads"]["samples"] > 0 and result["outside"]["samples"] > 0
    assert (tmp_path / "out" / "load-while-streaming-files.md").exists()
