"""A loaded bone: the voxel grid, its material table, and where it came from."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .grid import BoneGrid
from .materials import MaterialTable


@dataclass
class Bone:
    """A voxel bone ready for a :class:`~.engine.BoneEngine`.

    Attributes:
        grid: the voxels (world frame: LPS millimetres for loaded scans).
        materials: what each label is.
        name: the file or phantom it came from.
        format: how it was read ("nrrd", "dicom", "phantom", …).
        kind: what the voxels meant: "ct" (HU), "labels", "density" or "bone" (our format).
        notes: what the loader assumed or changed (an axis flipped, a unit assumed, …).
    """

    grid: BoneGrid
    materials: MaterialTable
    name: str = ""
    format: str = ""
    kind: str = ""
    notes: list[str] = field(default_factory=list)

    def volumes_mm3(self) -> dict[str, float]:
        """Bone left per material, mm³: every material in the table, and any label in the
        voxels that has none (as ``label N``)."""
        per_label = self.grid.bone_volume_by_label_mm3()
        labels = set(self.materials.labels()) | set(np.flatnonzero(per_label).tolist())
        labels.discard(0)
        return {self.materials.name_of(label): float(per_label[label])
                for label in sorted(labels)}

    def info(self) -> dict:
        """A JSON-ready summary: geometry, materials and their volumes, provenance."""
        grid = self.grid
        lo, hi = grid.bounds_mm()
        return {
            "name": self.name,
            "format": self.format,
            "kind": self.kind,
            "shape": list(grid.shape),
            "spacing_mm": grid.spacing_mm.tolist(),
            "origin_mm": grid.origin_mm.tolist(),
            "direction": grid.direction.tolist(),
            "frame": "LPS" if self.format not in ("phantom", "") else "phantom",
            "bounds_mm": [lo.tolist(), hi.tolist()],
            "materials": self.volumes_mm3(),
            "material_table": [
                {"label": label, "name": m.name, "us_n_mm2": m.us_n_mm2, "k": m.k,
                 "forbidden": m.forbidden}
                for label, m in self.materials],
            "bone_version": grid.version,
            "memory_bytes": int(grid.density.nbytes + grid.labels.nbytes + grid.swept.nbytes),
            "notes": list(self.notes),
        }
