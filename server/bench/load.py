"""``burrforce bench load``: load time and memory of a large volume in every format.

A temporal-bone phantom is padded into an N³ grid (default 512³ = 134 M voxels), written with
each format's own library, and loaded back in a fresh process per run so that the peak resident
memory is the load's own (the process's baseline — Python, NumPy, numba, the format libraries
— is measured apart and reported beside it).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..argtypes import int_in
from . import runner
from .timing import machine_line

#: The formats timed: keys of bone_files.FORMAT_WRITERS.
FORMATS = ("bone", "npz", "nrrd", "seg.nrrd", "nifti", "nifti-ct", "dicom", "png")
DEFAULT_SIZE = 512


@dataclass(frozen=True)
class LoadRow:
    format: str
    shape: tuple[int, int, int]
    file_mb: float
    write_s: float
    load_s_median: float
    load_s_min: float
    peak_rss_mb: float
    baseline_rss_mb: float
    bone_mm3: float


def build_bone(size: int):
    """The temporal-bone phantom padded into a size³ grid of the same voxel size."""
    from ..bone.bone import Bone
    from ..bone.grid import BoneGrid
    from ..bone.phantoms import temporal_bone

    probe = temporal_bone(1.0)
    voxel_mm = float(max(probe.grid.shape) * probe.grid.spacing_mm[0]) / size
    bone = temporal_bone(voxel_mm)
    shape = bone.grid.shape
    if max(shape) > size:
        raise ValueError(f"the phantom is {shape} at {voxel_mm:.4f} mm, larger than {size}³")
    density = np.zeros((size,) * 3, dtype=np.uint8)
    labels = np.zeros_like(density)
    box = tuple(slice(0, n) for n in shape)
    density[box] = bone.grid.density
    labels[box] = bone.grid.labels
    grid = BoneGrid(density, bone.grid.spacing_mm, origin_mm=bone.grid.origin_mm,
                    labels=labels)
    return Bone(grid, bone.materials, name=f"temporal phantom in {size}³", format="phantom")


def _size_mb(path: Path) -> float:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.iterdir()) / 1e6
    return path.stat().st_size / 1e6


def run(size: int, formats: tuple[str, ...], repeats: int, workdir: Path,
        progress=None) -> list[LoadRow]:
    say = progress or (lambda text: None)
    say(f"building the {size}³ phantom")
    bone = build_bone(size)
    spacing = ",".join(repr(float(s)) for s in bone.grid.spacing_mm)
    mapping = workdir / "materials.toml"
    from . import bone_files
    mapping.write_text(bone_files.materials_toml(bone))
    baseline = _child(["--baseline"])["peak_rss_mb"]
    rows = []
    for fmt in formats:
        say(f"{fmt}: writing")
        t0 = time.perf_counter()
        path = bone_files.write(bone, fmt, workdir)
        write_s = time.perf_counter() - t0
        args = [str(path), "--materials", str(mapping), "--spacing", spacing]
        _child(args)  # warm the numba cache and the page cache
        results = []
        for i in range(repeats):
            say(f"{fmt}: load {i + 1}/{repeats}")
            results.append(_child(args))
        times = [r["load_s"] for r in results]
        rows.append(LoadRow(fmt, bone.grid.shape, round(_size_mb(path), 2), round(write_s, 2),
                            round(float(np.median(times)), 3), round(min(times), 3),
                            round(max(r["peak_rss_mb"] for r in results), 1),
                            round(baseline, 1), round(results[0]["bone_mm3"], 1)))
        _remove(path)
    return rows


def _remove(path: Path) -> None:
    if path.is_dir():
        for p in path.iterdir():
            p.unlink()
        path.rmdir()
    else:
        path.unlink()


def _child(args: list[str]) -> dict:
    """Run one load in a fresh interpreter; its JSON result."""
    out = subprocess.run([sys.executable, "-c",
                          "from burrforce.server.bench.load import child; child()", *args],
                         capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"load subprocess failed: {out.stderr.strip()[-2000:]}")
    return json.loads(out.stdout)


def child() -> None:
    """In the child: load sys.argv[1] and print the time, peak RSS and bone volume."""
    import resource

    from ..bone.loaders import LoadOptions, load_bone
    from ..bone.material_map import MaterialMap

    argv = sys.argv[1:]
    if argv == ["--baseline"]:
        print(json.dumps({"peak_rss_mb": _peak_rss_mb(resource)}))
        return
    path, _, materials, _, spacing = argv
    options = LoadOptions(materials=MaterialMap.from_file(materials),
                          spacing_mm=tuple(float(s) for s in spacing.split(","))
                          if path.endswith("png") else None)
    t0 = time.perf_counter()
    bone = load_bone(path, options)
    load_s = time.perf_counter() - t0
    print(json.dumps({"load_s": load_s, "peak_rss_mb": _peak_rss_mb(resource),
                      "bone_mm3": sum(bone.volumes_mm3().values())}))


def _peak_rss_mb(resource) -> float:
    """This process's peak resident memory, MB. VmHWM, not getrusage's ru_maxrss: Linux keeps
    ru_maxrss across fork + exec, so a child would report its parent's (the parent holds the
    512³ bone) peak."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def render_markdown(rows: list[LoadRow], command: str) -> str:
    n = rows[0].shape[0] if rows else 0
    lines = [
        f"# Loading a {n}³ bone",
        "",
        f"Run: `{command}` on {dt.date.today().isoformat()}, {machine_line()}.",
        "",
        f"A temporal-bone phantom padded into {n}³ voxels ({n ** 3 / 1e6:.0f} M), written by "
        "each format's own library (`server/bench/bone_files.py`), loaded by `load_bone` in a "
        "fresh process per run after one warm-up load (numba cache and page cache warm). Peak "
        "RSS is the whole process; the baseline is the same interpreter after importing the "
        "loaders, before loading anything. The finished bone holds 3 bytes per voxel "
        f"({3 * n ** 3 / 1e6:.0f} MB). The phantom is mostly air and noise-free, so the "
        "compressed files are small: a real CT's noise compresses far worse and reads slower.",
        "",
        "| format | file MB | write s | load s (median) | load s (min) | peak RSS MB | "
        "RSS above baseline MB | bone mm³ |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r.format} | {r.file_mb:.1f} | {r.write_s:.1f} | "
                     f"{r.load_s_median:.2f} | {r.load_s_min:.2f} | {r.peak_rss_mb:.0f} | "
                     f"{r.peak_rss_mb - r.baseline_rss_mb:.0f} | {r.bone_mm3:.1f} |")
    lines.append("")
    return "\n".join(lines)


def _formats(text: str) -> tuple[str, ...]:
    chosen = tuple(part.strip() for part in text.split(",") if part.strip())
    unknown = [f for f in chosen if f not in FORMATS]
    if unknown or not chosen:
        raise argparse.ArgumentTypeError(f"formats are {', '.join(FORMATS)}; got {text!r}")
    return chosen


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "load", main, help="load time and memory of a 512³ bone in every format",
        description="Write a phantom padded to N³ voxels in every format and time loading it "
                    "back (fresh process per load: peak memory). Writes OUT/load.md and "
                    "load.json.", json_help="print the rows as JSON on stdout")
    p.add_argument("--size", type=int_in(32, 1024, "size"), default=DEFAULT_SIZE,
                   help=f"voxels per side. Default {DEFAULT_SIZE}")
    p.add_argument("--formats", type=_formats, default=FORMATS,
                   help=f"comma-separated subset of {','.join(FORMATS)}")
    p.add_argument("--repeats", type=int_in(1, 20, "repeats"), default=3,
                   help="loads per format. Default 3")


def main(args: argparse.Namespace) -> int:
    flags = [] if args.size == DEFAULT_SIZE else [f"--size {args.size}"]
    if args.formats != FORMATS:
        flags.append("--formats " + ",".join(args.formats))
    if args.repeats != 3:
        flags.append(f"--repeats {args.repeats}")
    command = " ".join(["burrforce bench load", *flags])
    out = runner.out_dir(args)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="burrforce-load-") as tmp:
        rows = run(args.size, args.formats, args.repeats, Path(tmp), progress=runner.say)
    (out / "load.md").write_text(render_markdown(rows, command))
    (out / "load.json").write_text(json.dumps(
        {"command": command, "machine": machine_line(), "date": dt.date.today().isoformat(),
         "rows": [asdict(r) for r in rows]}, indent=2))
    return runner.report(args, out / "load.md", out / "load.json",
                         rows=[asdict(r) for r in rows])
