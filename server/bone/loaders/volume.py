"""What a format reader hands on: voxel values with their geometry, before they become bone."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..material_map import Segment
from .slabs import VoxelSource

#: What a volume's values mean. "auto" lets :mod:`.convert` decide from the values.
KINDS = ("auto", "ct", "labels", "density")
#: The most voxels a loader accepts: 1024³. A 512³ scan is 134 M.
MAX_LOAD_VOXELS = 1 << 30

#: progress(stage, done, total): stage names the step ("reading", "converting").
Progress = Callable[[str, int, int], None]


@dataclass
class RawVolume:
    """Voxel values as read, with their geometry in LPS millimetres.

    Attributes:
        path: the file or directory read.
        format: the reader ("npy", "nrrd", "nifti", "dicom", "png").
        data: (nx, ny, nz) values: HU, label values, uint8 density or fractions in [0, 1]; an
            array, or a :class:`~.slabs.VoxelSource` that reads them a block at a time.
        spacing_mm: (3,) voxel size along the array axes, mm.
        origin_mm: (3,) world position of voxel (0, 0, 0)'s centre, mm.
        direction: (3, 3) unit grid axes as columns; may be a reflection until
            :func:`.geometry.right_handed`.
        kind: what the file says the values are, one of KINDS.
        segments: what the file says about label values (segment names, colours).
        labels: (nx, ny, nz) label values beside a density volume (npz, colour PNG), or
            None; an array or a source, like ``data``.
        numbered_by_reader: the label values are the reader's own numbering of segments or
            colours (seg.nrrd, colour PNGs), not the file's: materials match them by name or
            colour only.
        notes: assumptions made while reading.
    """

    path: Path
    format: str
    data: np.ndarray | VoxelSource
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    direction: np.ndarray
    kind: str = "auto"
    segments: dict[int, Segment] = field(default_factory=dict)
    labels: np.ndarray | VoxelSource | None = None
    numbered_by_reader: bool = False
    notes: list[str] = field(default_factory=list)
