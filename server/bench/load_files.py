"""Bone files loaded into a running ``burrforce serve`` as a client loads them — uploaded,
then a session created on the upload — each measured: the answer, how long it took, and the
control plane's peak resident memory while it loaded (``rss.PeakRss``).

:func:`synthetic_files` writes the files a memory bound is checked with: float64 CTs of 512³
and 1024³ voxels and 8 GiB uint8 gzip bombs, as gzip NRRD and ``.nii.gz``, a few megabytes
each (``large_volumes``).
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import httpx
import numpy as np

from .large_volumes import SUFFIXES, write_bomb, write_ct
from .rss import PeakRss, rss_bytes

#: Bytes a bomb inflates to.
BOMB_BYTES = 8 << 30
#: Sizes of the synthetic float64 CTs.
CT_SIZES = (512, 1024)
#: Round trips sent within this of a load's answer still count as during it, s.
FILE_TAIL_S = 0.2


def synthetic_files(folder: Path, sizes: tuple[int, ...] = CT_SIZES,
                    bomb_bytes: int = BOMB_BYTES) -> list[Path]:
    """Write the synthetic files into ``folder`` (seconds each: a 1024³ CT is 8 GiB of values
    to checksum): per format, the CTs in ``sizes`` order, then the bomb."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for fmt, suffix in SUFFIXES.items():
        for size in sizes:
            out.append(write_ct(folder / f"ct-{size}-float64{suffix}", size, fmt))
        out.append(write_bomb(folder / f"bomb-{bomb_bytes >> 30}GiB-uint8{suffix}", 1024,
                              bomb_bytes, fmt))
    return out


def kind_of(path: Path) -> str:
    """The kind a synthetic file is loaded as: its name says (a bomb as density, a CT as ct);
    any other file as CT."""
    return "density" if path.name.startswith("bomb-") else "ct"


def load_file(api: httpx.Client, pid: int, path: Path, kind: str,
              session_id: int) -> dict:
    """Upload ``path``, create session ``session_id`` on it (waiting for the load) while
    measuring the resident memory of the server process ``pid``, then delete the session
    and the upload.

    Returns:
        name, bytes, kind, status and detail of the session's creation, load_s (from the
        request to its answer), rss_before and peak_rss (bytes), peak_exact (the kernel's
        peak), shape of the loaded bone (None when refused), t_start_ns and t_end_ns
        (monotonic: when the load ran), t_deleted_ns (when the session was deleted, a
        while after: start and end).
    """
    with open(path, "rb") as f:
        up = api.post("/uploads", params={"filename": path.name}, content=f)
    up.raise_for_status()
    source = up.json()["source"]
    body = {"id": session_id, "bone": {"source": source, "kind": kind}}
    with PeakRss(pid) as peak:
        t0 = time.monotonic_ns()
        r = api.post("/sessions", params={"wait": "true"}, json=body)
        t1 = time.monotonic_ns()
    shape, deleted = None, (t1, t1)
    if r.status_code in (201, 202):
        shape = r.json().get("bone", {}).get("shape")
        # Apart from the load: dropping a large bone (the hot loop unmaps it) is not loading.
        time.sleep(2 * FILE_TAIL_S)
        d0 = time.monotonic_ns()
        api.delete(f"/sessions/{session_id}").raise_for_status()
        deleted = (d0, time.monotonic_ns())
    detail = r.json().get("detail", "") if r.status_code >= 400 else ""
    if isinstance(detail, list):  # the API's 422 form: [{"loc": …, "msg": …}]
        detail = "; ".join(str(d.get("msg", d)) for d in detail)
    # The server names the upload by its path in the data directory: name the file instead.
    detail = re.sub(r"\S*/uploads/[0-9a-f]{16}[.\w]*", path.name, str(detail))
    api.delete(f"/uploads/{source.split(':', 1)[1]}", params={"force": "true"})
    return {"name": path.name, "bytes": path.stat().st_size, "kind": kind,
            "status": r.status_code, "detail": detail, "load_s": round((t1 - t0) / 1e9, 3),
            "rss_before": peak.before, "peak_rss": peak.peak, "peak_exact": peak.exact,
            "shape": shape, "t_start_ns": t0, "t_end_ns": t1, "t_deleted_ns": deleted}


def rtt_stats(rtt_us: np.ndarray) -> dict[str, float | int]:
    """Samples, p50, p99 and max of round trips, µs."""
    if len(rtt_us) == 0:
        return {"samples": 0}
    return {"samples": len(rtt_us), "p50_us": float(np.median(rtt_us)),
            "p99_us": float(np.percentile(rtt_us, 99)), "max_us": float(rtt_us.max())}


def run_files(paths: list[Path], quiet_s: float, rate_hz: float = 1000.0,
              load_budget: int | None = None, progress=None) -> dict:
    """``burrforce serve`` (the workpiece in session 1) with a client streaming session 1 at
    ``rate_hz`` from a process of its own, while each of ``paths`` is uploaded and loaded into
    session 2 in turn (``load_file``), ``quiet_s`` apart. ``load_budget``: serve's
    ``load_budget_bytes`` (None: its default).

    Returns:
        rate_hz, load_budget_bytes (0: each load's bone + 512 MiB), server_rss_start (bytes),
        files (``load_file``'s rows with the round trips sent during each load: lost,
        samples, max_us; and while its session was deleted: delete_s, delete_lost,
        delete_max_us), replies (samples and lost over the whole run), during_loads and
        outside (round-trip statistics and lost; outside leaves out the deletions).
    """
    import shutil
    import subprocess
    import sys
    import tempfile

    from .serve_process import spawn_serve

    say = progress or (lambda text: None)
    work = Path(tempfile.mkdtemp(prefix="burrforce-lfs-"))
    env = {"BURRFORCE_LOAD_BUDGET_BYTES": str(load_budget or 0)}
    rows, windows, deletions = [], [], []
    try:
        say("starting burrforce serve")
        serve = spawn_serve(work, "--bone", "phantom:workpiece", env=env)
        pid = serve.proc.pid
        start_rss = rss_bytes(pid) or 0
        try:
            c = serve.connection
            samples = work / "rtt.npy"
            budget_s = quiet_s * (len(paths) + 2) + 300.0 * len(paths)
            client = subprocess.Popen(
                [sys.executable, "-m", "burrforce.server.bench.load_while_streaming",
                 c.host, str(c.udp_port), c.key_hex or "", str(budget_s), str(rate_hz),
                 str(samples)])
            time.sleep(quiet_s + 1.0)  # the client's start-up, then a quiet spell
            with httpx.Client(base_url=f"{c.http_url}/v1", timeout=600.0,
                              headers={"Authorization": f"Bearer {c.token}"}) as api:
                for n, path in enumerate(paths):
                    say(f"file {n + 1}/{len(paths)}: {path.name}")
                    row = load_file(api, pid, path, kind_of(path), 2)
                    say(f"  {row['status']} in {row['load_s']} s, peak RSS "
                        f"{row['peak_rss'] / 2**20:.0f} MiB {row['detail'][:120]}")
                    rows.append(row)
                    windows.append((row.pop("t_start_ns"), row.pop("t_end_ns")))
                    deletions.append(row.pop("t_deleted_ns"))
                    time.sleep(quiet_s)
            client.terminate()
            client.wait()
        finally:
            serve.stop()
        data = np.load(samples)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    sent, rtt = data[:, 0], data[:, 1]
    lost = np.isnan(rtt)
    during = np.zeros(len(sent), dtype=bool)
    tail = FILE_TAIL_S * 1e9
    for row, (t0, t1), (d0, d1) in zip(rows, windows, deletions, strict=True):
        this = (sent >= t0) & (sent <= t1 + tail)
        gone = (sent >= d0) & (sent <= d1 + tail) & (d1 > d0)
        during |= this
        row.update({"samples": int(this.sum()), "lost": int((this & lost).sum()),
                    "max_us": round(float(np.nanmax(rtt[this], initial=0.0))),
                    "delete_s": round((d1 - d0) / 1e9, 3),
                    "delete_lost": int((gone & lost).sum()),
                    "delete_max_us": round(float(np.nanmax(rtt[gone], initial=0.0)))})
    near = np.zeros(len(sent), dtype=bool)
    for (t0, t1), (_, d1) in zip(windows, deletions, strict=True):
        near |= (sent >= t0 - tail) & (sent <= max(t1, d1) + 2 * tail)
    outside = ~near & (sent >= windows[0][0] - quiet_s * 1e9) if windows else ~near
    return {"rate_hz": rate_hz, "load_budget_bytes": int(load_budget or 0),
            "server_rss_start": start_rss, "files": rows,
            "replies": {"samples": len(sent), "lost": int(lost.sum())},
            "during_loads": rtt_stats(rtt[during & ~lost]) | {"lost": int((during & lost).sum())},
            "outside": rtt_stats(rtt[outside & ~lost]) | {"lost": int((outside & lost).sum())}}


def page_lines(result: dict) -> list[str]:
    """The results page of :func:`run_files`."""
    mib = 1 << 20
    budget = result["load_budget_bytes"]
    lines = [
        "# Bone files loaded while a session streams (`burrforce bench load-while-streaming "
        "--file`)",
        "",
        f"{result['date']}; {result['machine']}. `burrforce serve` with the workpiece in "
        f"session 1, cut at {result['rate_hz']:g} Hz by a client process of its own; each "
        "file is uploaded and a session created on it (`POST /v1/sessions?wait=true`). Peak "
        "RSS: the control plane's (the serve process) while the session was created. A loaded "
        "session is deleted 0.4 s after its answer; the round trips meanwhile are counted "
        "apart (the hot loop unmapping a bone is not a load). Load "
        "budget: " + (f"{budget / mib:,.0f} MiB (load_budget_bytes)" if budget else
                      "each load's bone (3 bytes a voxel) + 512 MiB") + f"; the server "
        f"started at {result['server_rss_start'] / mib:,.0f} MiB.",
        "",
        "| file | MB | kind | answer | s | RSS before MiB | peak RSS MiB | replies during | "
        "lost | max round trip ms | deleting it: s, lost, max round trip ms |",
        "|---|---:|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in result["files"]:
        detail = r["detail"] if len(r["detail"]) <= 200 else r["detail"][:200] + "…"
        answer = str(r["status"]) + (f": {detail}" if detail else "")
        lines.append(f"| {r['name']} | {r['bytes'] / 1e6:.1f} | {r['kind']} | {answer} | "
                     f"{r['load_s']} | {r['rss_before'] / mib:,.0f} | {r['peak_rss'] / mib:,.0f}"
                     f" | {r['samples']} | {r['lost']} | {r['max_us'] / 1000:.1f} | "
                     + (f"{r['delete_s']}, {r['delete_lost']}, "
                        f"{r['delete_max_us'] / 1000:.1f} |" if r["delete_s"] else "– |"))
    d, o = result["during_loads"], result["outside"]

    def row(name: str, s: dict) -> str:
        if not s["samples"]:
            return f"| {name} | 0 | {s['lost']} | – | – | – |"
        return (f"| {name} | {s['samples']} | {s['lost']} | {s['p50_us']:.0f} | "
                f"{s['p99_us']:.0f} | {s['max_us']:.0f} |")

    lines += ["", "| streaming session | samples | lost | p50 µs | p99 µs | max µs |",
              "|---|---:|---:|---:|---:|---:|", row("during the loads", d),
              row("outside them", o), "",
              f"Replies lost over the whole run: {result['replies']['lost']} of "
              f"{result['replies']['samples']}."]
    return lines
