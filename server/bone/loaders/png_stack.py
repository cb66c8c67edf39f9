"""PNG slice stacks: a folder of ``*.png``, one slice per file, spacing from the caller.

The layout volumetric_drilling (AMBF) uses: slice k is the k-th file in natural order
(``plane2.png`` before ``plane10.png``), and pixel (row r, column c) of a slice is voxel
(r, c, k). Grayscale slices (8 or 16 bit) are values for the converter (density, labels or CT
by their kind); RGB(A) slices are segmentations: alpha (or any non-black colour) is occupancy
and each colour is a segment, matched to materials by the materials file's ``colors``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..material_map import Segment
from .budget import STREAM_WORK_BYTES, bone_bytes, budget_bytes
from .convert import LoadOptions, check_size
from .errors import BoneFileError
from .slabs import SliceSource
from .volume import Progress, RawVolume

_GRAY_MODES = {"L": np.uint8, "I;16": np.uint16, "I;16B": np.uint16, "I": np.int32,
               "1": np.uint8}
_COLOUR_MODES = ("RGB", "RGBA", "P", "LA")


def natural_key(path: Path) -> list:
    return [int(part) if part.isdigit() else part.lower()
            for part in re.split(r"(\d+)", path.name)]


def read_png_stack(path: Path, options: LoadOptions, progress: Progress | None) -> RawVolume:
    """A folder of PNG slices. Grey slices are decoded as the converter reaches them; colour
    slices once here, for their palette (and kept decoded when that fits the load budget)."""
    if not path.is_dir():
        raise BoneFileError(path, "a PNG stack is read from its folder: give the folder")
    files = sorted((p for p in path.iterdir() if p.suffix.lower() == ".png"
                    and not p.name.startswith(".")), key=natural_key)
    if not files:
        raise BoneFileError(path, "no .png files in the folder")
    if options.spacing_mm is None:
        raise BoneFileError(path, "PNG slices carry no voxel size: give spacing_mm "
                                  "(--spacing-mm)")
    first = _open(files[0])
    width, height = first.size
    mode = first.mode
    shape = (height, width, len(files))
    check_size(path, shape, options)
    colour = mode in _COLOUR_MODES
    if not colour and mode not in _GRAY_MODES:
        raise BoneFileError(files[0], f"unsupported PNG mode {mode}")
    n = len(files)
    spacing = np.asarray(options.spacing_mm, dtype=np.float64)
    origin = np.zeros(3)  # the converter applies options.origin_mm (and notes it)
    notes = [f"{n} PNG slices in natural file-name order; identity orientation"]
    slice_bytes = width * height * 16  # a decoded slice: RGBA, packed colours, masks

    def open_slice(k: int) -> Image.Image:
        image = _open(files[k])
        if image.size != (width, height) or image.mode != mode:
            raise BoneFileError(files[k], f"{image.size[0]}×{image.size[1]} {image.mode} "
                                          f"differs from the first slice's {width}×{height} "
                                          f"{mode}")
        return image

    if not colour:
        def grey(k: int) -> np.ndarray:
            try:
                return np.asarray(open_slice(k), dtype=_GRAY_MODES[mode])
            except (OSError, ValueError, SyntaxError) as exc:
                raise BoneFileError(files[k], f"the image data is damaged or truncated: "
                                              f"{exc}") from None
        data = SliceSource(grey, shape, np.dtype(_GRAY_MODES[mode]), slice_bytes)
        return RawVolume(path, "png", data, spacing, origin, np.eye(3), notes=notes)

    palette: dict[int, int] = {}

    def segmented(k: int) -> tuple[np.ndarray, np.ndarray]:
        try:
            return _segment_slice(files[k], open_slice(k), palette)
        except (OSError, ValueError, SyntaxError) as exc:
            raise BoneFileError(files[k], f"the image data is damaged or truncated: "
                                          f"{exc}") from None

    occupancy, values = _colour_volumes(path, shape, segmented, options, progress)
    segments = {v: Segment(color=((key >> 16) & 255, (key >> 8) & 255, key & 255))
                for key, v in palette.items()}
    return RawVolume(path, "png", occupancy, spacing, origin, np.eye(3), kind="density",
                     labels=values, segments=segments, numbered_by_reader=True, notes=notes)


def _colour_volumes(path: Path, shape: tuple[int, int, int], segmented,
                    options: LoadOptions, progress: Progress | None):
    """(occupancy, colour index) of a colour stack: arrays decoded in one pass when both fit
    the load budget beside the bone, else sources decoding the slices again per pass (the
    palette is complete after the first, so each pass numbers the colours alike)."""
    n = shape[2]
    held = 2 * int(np.prod(shape, dtype=np.int64))
    fits = (bone_bytes(shape) + STREAM_WORK_BYTES + held
            <= budget_bytes(shape, options.memory_budget_bytes))
    occupancy = np.empty(shape, dtype=np.uint8) if fits else None
    values = np.empty(shape, dtype=np.uint8) if fits else None
    for k in range(n):
        o, v = segmented(k)
        if occupancy is not None and values is not None:
            occupancy[:, :, k], values[:, :, k] = o, v
        if progress is not None:
            progress("reading", k + 1, n)
    if occupancy is not None and values is not None:
        return occupancy, values
    return (SliceSource(lambda k: segmented(k)[0], shape, np.dtype(np.uint8)),
            SliceSource(lambda k: segmented(k)[1], shape, np.dtype(np.uint8)))


def _open(file: Path) -> Image.Image:
    try:
        image = Image.open(file)
        image.load()
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError,
            Image.DecompressionBombError) as exc:
        raise BoneFileError(file, f"not a readable PNG: {exc}") from None
    return image


def _segment_slice(file: Path, image: Image.Image, palette: dict[int, int]):
    """(occupancy uint8, colour index uint8) of one colour slice; new colours join
    ``palette`` (packed 0xRRGGBB → index 1..255)."""
    rgba = np.asarray(image.convert("RGBA"))
    rgb = rgba[..., :3].astype(np.uint32)
    packed = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    alpha = rgba[..., 3]
    # RGB slices (alpha all 255) mark empty space black; RGBA ones by alpha 0.
    occupancy = np.where(packed > 0, alpha, 0).astype(np.uint8) if image.mode in ("RGB", "P") \
        else alpha.copy()
    occupied = occupancy > 0
    values = np.zeros(packed.shape, dtype=np.uint8)
    # A segmentation has a handful of colours: one comparison per known colour beats sorting
    # every pixel (np.unique) on every slice.
    for key, index in palette.items():
        values[occupied & (packed == key)] = index
    new = occupied & (values == 0)
    if new.any():
        for key in np.unique(packed[new]).tolist():
            if len(palette) >= 255:
                raise ValueError("more than 255 colours: not a segmentation")
            palette[key] = len(palette) + 1
            values[new & (packed == key)] = palette[key]
    return occupancy, values
