"""``burrforce bone``: inspect and convert bone files."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..bone.bone import Bone
from ..bone.loaders import FORMATS, LoadOptions, load_bone, save_bone
from ..bone.loaders.volume import KINDS
from ..bone.material_map import MaterialMap

PHANTOM_PREFIX = "phantom:"


def _triple(text: str) -> tuple[float, float, float]:
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 1 or 3 comma-separated numbers in mm, got "
                                         f"{text!r}") from None
    if len(values) == 1:
        values *= 3
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected 1 or 3 numbers, got {text!r}")
    return tuple(values)  # type: ignore[return-value]


def _add_load_options(p: argparse.ArgumentParser) -> None:
    from ..bone.phantoms import PHANTOMS

    p.add_argument("path", metavar="PATH",
                   help=f"a bone file or folder ({', '.join(FORMATS)}), or "
                        f"{PHANTOM_PREFIX}NAME for a built-in phantom "
                        f"({', '.join(PHANTOMS)})")
    p.add_argument("--kind", choices=KINDS, default="auto",
                   help="what the voxel values are: ct (HU), labels, density (0–255 or "
                        "fractions). Default auto (from the file and its values)")
    p.add_argument("--spacing-mm", type=_triple, metavar="S|SX,SY,SZ",
                   help="voxel size in mm: needed for .npy and PNG stacks; overrides others")
    p.add_argument("--origin-mm", type=_triple, metavar="X,Y,Z",
                   help="first voxel's centre in mm, for .npy and PNG stacks")
    p.add_argument("--materials", type=Path, metavar="FILE",
                   help="materials file (TOML or JSON): label values, segment names and "
                        "colours → materials; HU bands for CT")
    p.add_argument("--material", default="cortical",
                   help="material of a density volume without labels. Default cortical")
    p.add_argument("--series", metavar="UID",
                   help="the DICOM series to read when a folder holds several")
    p.add_argument("--voxel-mm", type=float, metavar="MM",
                   help="voxel size of a built-in phantom, mm")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bone", help="inspect and convert bone files (CT, segmentations)")
    bone_sub = p.add_subparsers(dest="bone_command", metavar="ACTION", required=True)
    info = bone_sub.add_parser(
        "info", help="what a bone file holds: geometry and bone volume per material",
        description="Load a bone file and print its geometry (LPS millimetres) and the bone "
                    "volume of each material.")
    _add_load_options(info)
    info.add_argument("--json", action="store_true", help="print a JSON object")
    info.set_defaults(func=_run_info)
    convert = bone_sub.add_parser(
        "convert", help="write a bone file in burrforce's compact format (.bone.npz)",
        description="Load any bone file and write it as a .bone.npz: voxels, geometry and "
                    "materials in one compressed file that loads fast.")
    _add_load_options(convert)
    convert.add_argument("output", type=Path, metavar="OUTPUT",
                         help="the .bone.npz to write (the suffix is added if missing)")
    convert.set_defaults(func=_run_convert)


def load_from_args(args: argparse.Namespace) -> Bone:
    """Load the bone the arguments name, with a progress bar on a terminal."""
    text = str(args.path)
    if text.startswith(PHANTOM_PREFIX):
        from ..bone.phantoms import phantom
        file_options = [flag for flag, value, default in (
            ("--kind", args.kind, "auto"), ("--spacing-mm", args.spacing_mm, None),
            ("--origin-mm", args.origin_mm, None), ("--materials", args.materials, None),
            ("--material", args.material, "cortical"), ("--series", args.series, None))
            if value != default]
        if file_options:
            verb = "is" if len(file_options) == 1 else "are"
            raise ValueError(f"{', '.join(file_options)} {verb} for files, not for a built-in "
                             "phantom (it has its own geometry and materials; --voxel-mm sets "
                             "its voxel size)")
        return phantom(text[len(PHANTOM_PREFIX):], args.voxel_mm)
    if args.voxel_mm is not None:
        raise ValueError("--voxel-mm sets a phantom's voxel size; for a file use --spacing-mm")
    materials = MaterialMap.from_file(args.materials) if args.materials else MaterialMap()
    options = LoadOptions(kind=args.kind, spacing_mm=args.spacing_mm, origin_mm=args.origin_mm,
                          materials=materials, material=args.material, series_uid=args.series)
    with _ProgressBar() as bar:
        return load_bone(Path(text), options, bar)


class _ProgressBar:
    """tqdm bars on stderr, one per stage; silent when stderr is not a terminal."""

    def __init__(self) -> None:
        self._bar = None
        self._stage = ""

    def __call__(self, stage: str, done: int, total: int) -> None:
        from tqdm import tqdm
        if stage != self._stage:
            self.close()
            self._stage = stage
            self._bar = tqdm(total=total, desc=stage, unit="slice", file=sys.stderr,
                             disable=None, leave=False)
        if self._bar is not None and done > self._bar.n:
            self._bar.update(done - self._bar.n)  # redraws at most every 0.1 s

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> _ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _run_info(args: argparse.Namespace) -> int:
    bone = load_from_args(args)
    info = bone.info()
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(format_info(info))
    return 0


def format_info(info: dict) -> str:
    def vec(values: list[float]) -> str:
        return "(" + ", ".join(f"{v:.6g}" for v in values) + ")"

    lines = [
        f"{info['name']}",
        f"  format {info['format']}, read as {info['kind']}",
        f"  shape {tuple(info['shape'])} voxels of {vec(info['spacing_mm'])} mm",
        f"  origin {vec(info['origin_mm'])} mm ({info['frame']}), bounds "
        f"{vec(info['bounds_mm'][0])} – {vec(info['bounds_mm'][1])} mm",
        f"  {info['memory_bytes'] / 1e6:.1f} MB in memory",
        "  label  material              Us N/mm²      K  forbidden     bone mm³",
    ]
    listed = set()
    for row in info["material_table"]:
        listed.add(row["name"])
        lines.append(f"  {row['label']:>5}  {row['name'][:20]:<20} {row['us_n_mm2']:>10.1f} "
                     f"{row['k']:>6.2f}  {'yes' if row['forbidden'] else 'no':<9} "
                     f"{info['materials'].get(row['name'], 0.0):>12.1f}")
    for name, volume in info["materials"].items():
        if name not in listed:
            lines.append(f"      -  {name[:20]:<20} {'(no material: cuts with Us = 0)':<28}"
                         f"{volume:>12.1f}")
    lines += [f"  note: {note}" for note in info["notes"]]
    return "\n".join(lines)


def _run_convert(args: argparse.Namespace) -> int:
    folder = args.output.parent
    try:  # before the load, which can take seconds
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"cannot write {args.output}: {exc.strerror}") from None
    bone = load_from_args(args)
    path = save_bone(bone, args.output)
    total = sum(bone.volumes_mm3().values())
    size = path.stat().st_size
    shown = f"{size / 1e6:.2f} MB" if size >= 1e6 else f"{size / 1e3:.1f} kB"
    print(f"wrote {path} ({shown}): {bone.grid.shape} voxels, "
          f"{len(bone.materials)} materials, {total:.1f} mm³ of bone")
    return 0
