"""Replaying a recording offline: the same engine inputs through a fresh engine.

With the recorded parameters the replay reproduces every tick bit for bit on the same
machine (same numba kernels, same inputs, same engine state): the report's deviations are all
zero. With overrides (Us scaled, another K, a material changed) it answers "what if": the same
hand movements against other bone. The motion is the recorded one either way — a replay does
not model how the trainee's hand would have reacted to other forces.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...proto import frames
from ...proto.messages import (
    STATUS_CONTACT,
    STATUS_CUTTING,
    STATUS_FORBIDDEN,
    STATUS_SHAFT_CONTACT,
)
from ..bone.bone import Bone
from ..bone.carve import TOUCH_FORBIDDEN
from ..bone.contact_status import contact_status
from ..bone.engine import BoneEngine, ShaftParams
from ..bone.loaders import BoneFileError, load_bone
from ..bone.materials import Material, MaterialTable
from ..bone.shaft import N_SHAFT, SHAFT_FORCE, SHAFT_TORQUE
from ..model.kernels import N_OUT, OUT_FORCE, OUT_POWER, OUT_TORQUE
from ..model.params import CuttingParams
from .format import (
    REC_CARVE_RESET,
    Recording,
    RecordingError,
    apply_start_patch,
    read_recording,
)

#: Status bits the bone stage sets (the others come from the pose and the velocity estimate,
#: which a replay takes as recorded).
MODEL_STATUS = STATUS_CUTTING | STATUS_CONTACT | STATUS_FORBIDDEN | STATUS_SHAFT_CONTACT
MATERIAL_FIELDS = ("us_n_mm2", "k", "forbidden")
PROGRESS_EVERY = 1000

CSV_COLUMNS = ("t_s", "seq", "status", "cutting", "fx_N", "fy_N", "fz_N", "force_N",
               "tx", "ty", "tz", "power_w", "removed_mm3", "bone_version",
               "recorded_force_N")


@dataclass
class ReplayReport:
    """What a replay found. Forces are the reply's (cut + shaft, N, engine frame); "while
    cutting" means ticks whose burr removed bone (``STATUS_CUTTING``).

    Per-tick arrays (length ``ticks``): ``t_s`` (from the first tick), ``seq``, ``status``,
    ``force`` and ``torque`` (n, 3), ``force_N`` (|force|), ``recorded_force_N``,
    ``removed_mm3_tick``, ``bone_version``, ``out`` (n, N_OUT) and ``shaft_out`` (n, N_SHAFT).
    """

    recording: Path
    ticks: int
    duration_s: float
    cutting_ticks: int
    removed_mm3: float
    removed_mm3_by_material: dict[str, float]
    forbidden_events: list[dict[str, Any]]
    mean_force_N: float
    max_force_N: float
    recorded_mean_force_N: float
    recorded_max_force_N: float
    max_deviation: dict[str, float]
    mismatched_ticks: int
    final_bone_version: int
    recorded_final_bone_version: int | None
    overrides: dict[str, Any]
    complete: bool
    problems: list[str]
    stopped_reason: str | None
    notes: list[str]
    bone: Bone = field(repr=False)
    t_s: np.ndarray = field(repr=False)
    seq: np.ndarray = field(repr=False)
    status: np.ndarray = field(repr=False)
    force: np.ndarray = field(repr=False)
    torque: np.ndarray = field(repr=False)
    force_N: np.ndarray = field(repr=False)
    recorded_force_N: np.ndarray = field(repr=False)
    removed_mm3_tick: np.ndarray = field(repr=False)
    bone_version: np.ndarray = field(repr=False)
    out: np.ndarray = field(repr=False)
    shaft_out: np.ndarray = field(repr=False)

    @property
    def reproduced(self) -> bool:
        """Every replayed tick equals the recorded one exactly."""
        return self.mismatched_ticks == 0 and all(v == 0.0 for v in self.max_deviation.values())

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (no per-tick arrays)."""
        return {
            "recording": str(self.recording),
            "ticks": self.ticks,
            "duration_s": self.duration_s,
            "cutting_ticks": self.cutting_ticks,
            "removed_mm3": self.removed_mm3,
            "removed_mm3_by_material": self.removed_mm3_by_material,
            "forbidden_events": self.forbidden_events,
            "mean_force_N": self.mean_force_N,
            "max_force_N": self.max_force_N,
            "recorded_mean_force_N": self.recorded_mean_force_N,
            "recorded_max_force_N": self.recorded_max_force_N,
            "max_deviation": self.max_deviation,
            "mismatched_ticks": self.mismatched_ticks,
            "reproduced": self.reproduced,
            "final_bone_version": self.final_bone_version,
            "recorded_final_bone_version": self.recorded_final_bone_version,
            "overrides": self.overrides,
            "complete": self.complete,
            "problems": self.problems,
            "stopped_reason": self.stopped_reason,
            "notes": self.notes,
        }

    def write_csv(self, path: str | Path) -> Path:
        """Per-tick forces (``CSV_COLUMNS``), one row per tick."""
        path = Path(path)
        power = self.out[:, OUT_POWER] * 1e-3
        with open(path, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(CSV_COLUMNS)
            for i in range(self.ticks):
                fx, fy, fz = self.force[i].tolist()
                tx, ty, tz = self.torque[i].tolist()
                status = int(self.status[i])
                w.writerow((repr(float(self.t_s[i])), int(self.seq[i]), status,
                            int(bool(status & STATUS_CUTTING)), repr(fx), repr(fy), repr(fz),
                            repr(float(self.force_N[i])), repr(tx), repr(ty), repr(tz),
                            repr(float(power[i])), repr(float(self.removed_mm3_tick[i])),
                            int(self.bone_version[i]),
                            repr(float(self.recorded_force_N[i]))))
        return path

    def format_text(self) -> str:
        """A human summary."""
        lines = [f"{self.recording}"]
        if self.overrides:
            lines.append("  what if: " + ", ".join(f"{k} = {v}" for k, v in
                                                   self.overrides.items()))
        lines.append(f"  {self.ticks} ticks over {self.duration_s:.3f} s, "
                     f"{self.cutting_ticks} cutting")
        removed = ", ".join(f"{name} {v:.4g}" for name, v in
                            self.removed_mm3_by_material.items()) or "none"
        lines.append(f"  removed {self.removed_mm3:.4g} mm³ ({removed})")
        lines.append(f"  |F| while cutting: mean {self.mean_force_N:.4g} N, max "
                     f"{self.max_force_N:.4g} N (recorded: mean "
                     f"{self.recorded_mean_force_N:.4g} N, max "
                     f"{self.recorded_max_force_N:.4g} N)")
        lines.append(f"  forbidden contacts: {len(self.forbidden_events)}")
        for e in self.forbidden_events[:20]:
            lines.append(f"    t = {e['t_s']:.3f} s: {e['material']} (label {e['label']})")
        if len(self.forbidden_events) > 20:
            lines.append(f"    … {len(self.forbidden_events) - 20} more")
        lines.append(f"  bone version {self.final_bone_version} (recorded "
                     f"{self.recorded_final_bone_version})")
        if self.reproduced:
            lines.append("  reproduced exactly: every force, torque and removal equals the "
                         "recording")
        else:
            dev = ", ".join(f"{k} {v:.3g}" for k, v in self.max_deviation.items())
            lines.append(f"  differs from the recording on {self.mismatched_ticks} ticks; "
                         f"max |Δ|: {dev}")
        if not self.complete:
            lines.append("  the recording is incomplete")
        if self.stopped_reason:
            lines.append(f"  recording stopped early: {self.stopped_reason}")
        lines.extend(f"  note: {n}" for n in self.notes)
        lines.extend(f"  problem: {p}" for p in self.problems)
        return "\n".join(lines)


def replay(
    recording: str | Path | Recording,
    us_scale: float = 1.0,
    k: float | None = None,
    materials: Mapping[str | int, Mapping[str, Any]] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ReplayReport:
    """Re-run a recording through a fresh engine and compare it with what was recorded.

    Args:
        recording: a ``.burrrec`` directory, or one already read.
        us_scale: multiply every material's Us by this.
        k: set every material's K to this.
        materials: per-material changes by name or label, e.g.
            ``{"cortical": {"us_n_mm2": 900.0}}`` (fields ``us_n_mm2``, ``k``, ``forbidden``);
            applied last, so they win over ``us_scale`` and ``k``.
        progress: called as progress(done, total) every 1000 ticks.

    Raises:
        RecordingError: the recording cannot be read or has no usable snapshot.
        ValueError: an override is out of range or names no material.
    """
    rec = recording if isinstance(recording, Recording) else read_recording(recording)
    meta = rec.meta
    if rec.snapshot is None:
        raise RecordingError(rec.path, "the recording has no start snapshot: it cannot be "
                                       "replayed")
    if not rec.snapshot.is_file():
        raise RecordingError(rec.path, f"the start snapshot {rec.snapshot.name} is missing")
    try:
        bone = load_bone(rec.snapshot)
    except BoneFileError as exc:
        raise RecordingError(rec.path, f"the start snapshot cannot be loaded: {exc}") from None
    apply_start_patch(rec.path, bone.grid)
    table, overrides = _materials(rec, us_scale, k, materials)
    bone.materials = table
    engine, tf = _engine(rec, bone, table)
    notes: list[str] = []
    if bone.grid.version != meta.get("bone_version", bone.grid.version):
        notes.append(f"the snapshot is bone version {bone.grid.version}, the recording "
                     f"started at {meta.get('bone_version')}")
    summary = rec.summary or {}
    if summary and not summary.get("resets_tracked", False):
        notes.append("the recorder was not attached with Recorder.attach: carving resets "
                     "were not recorded, so a replay may differ after a stream restart")

    rows = rec.rows
    n = len(rows)
    centre = np.ascontiguousarray(rows["centre_g"], dtype=np.float64)
    axis = np.ascontiguousarray(rows["axis_g"], dtype=np.float64)
    feed = np.ascontiguousarray(rows["feed_g"], dtype=np.float64)
    rpm = rows["rpm"].tolist()
    carve = rows["carve"].tolist()
    t_recv = rows["t_recv_ns"].tolist()
    resets = (rows["rec_flags"] & REC_CARVE_RESET).tolist()
    out = np.zeros((n, N_OUT))
    shaft = np.zeros((n, N_SHAFT))
    force = np.zeros((n, 3))
    torque = np.zeros((n, 3))
    removed_tick = np.zeros(n)
    version = np.zeros(n, dtype=np.int64)
    model_status = np.zeros(n, dtype=np.uint16)
    for i in range(n):
        if resets[i]:
            engine.forget_last_carve()
        removed = engine.step_raw(centre[i], axis[i], feed[i], rpm[i], carve[i])
        # The session's tick, from here on, as Session._tick computes it.
        o = engine.out.tolist()
        s = engine.shaft_out.tolist()
        st = contact_status(engine.out, engine.shaft_out, engine.touch[TOUCH_FORBIDDEN])
        engine.record_contact(t_recv[i] * 1e-9)
        if removed:
            removed_tick[i] = engine.removed_this_tick_mm3()
        out[i] = engine.out
        shaft[i] = engine.shaft_out
        fx, fy, fz = o[OUT_FORCE:OUT_FORCE + 3]
        sx, sy, sz = s[SHAFT_FORCE:SHAFT_FORCE + 3]
        force[i] = tf.direction_out((fx + sx, fy + sy, fz + sz))
        tx, ty, tz = o[OUT_TORQUE:OUT_TORQUE + 3]
        sx, sy, sz = s[SHAFT_TORQUE:SHAFT_TORQUE + 3]
        torque[i] = tf.torque_out((tx + sx, ty + sy, tz + sz))
        version[i] = engine.grid.version
        model_status[i] = st
        if progress is not None and (i + 1) % PROGRESS_EVERY == 0:
            progress(i + 1, n)
    if progress is not None:
        progress(n, n)

    recorded_status = rows["status"].astype(np.uint16)
    status = (recorded_status & ~np.uint16(MODEL_STATUS)) | model_status
    deviation = {
        "out": _max_abs(out, rows["out"]),
        "shaft_out": _max_abs(shaft, rows["shaft_out"]),
        "force_N": _max_abs(force, rows["force"]),
        "torque": _max_abs(torque, rows["torque"]),
        "removed_mm3": _max_abs(removed_tick, rows["removed_mm3"]),
        "bone_version": float(np.abs(version - rows["bone_version"]).max()) if n else 0.0,
    }
    same = (
        np.all(_bits(out) == _bits(rows["out"]), axis=1)
        & np.all(_bits(shaft) == _bits(rows["shaft_out"]), axis=1)
        & np.all(_bits(force) == _bits(rows["force"]), axis=1)
        & np.all(_bits(torque) == _bits(rows["torque"]), axis=1)
        & (_bits(removed_tick) == _bits(rows["removed_mm3"]))
        & (version == rows["bone_version"])
        & ((status & MODEL_STATUS) == (recorded_status & MODEL_STATUS))
    )
    force_n = np.sqrt((force * force).sum(axis=1))
    rec_force = np.asarray(rows["force"], dtype=np.float64)
    recorded_force_n = np.sqrt((rec_force * rec_force).sum(axis=1))
    cutting = (status & STATUS_CUTTING) != 0
    recorded_cutting = (recorded_status & STATUS_CUTTING) != 0
    t0 = t_recv[0] if n else 0
    t_s = (rows["t_recv_ns"] - t0) * 1e-9
    events = [{"t_s": e.time_s - t0 * 1e-9, "time_s": e.time_s, "label": e.label,
               "material": e.material, "position_mm": list(e.position_mm)}
              for e in engine.events]
    by_material = engine.removed_mm3_by_material()
    return ReplayReport(
        recording=rec.path,
        ticks=n,
        duration_s=float(t_s[-1]) if n else 0.0,
        cutting_ticks=int(cutting.sum()),
        removed_mm3=float(sum(by_material.values())),
        removed_mm3_by_material=by_material,
        forbidden_events=events,
        mean_force_N=float(force_n[cutting].mean()) if cutting.any() else 0.0,
        max_force_N=float(force_n[cutting].max()) if cutting.any() else 0.0,
        recorded_mean_force_N=float(recorded_force_n[recorded_cutting].mean())
        if recorded_cutting.any() else 0.0,
        recorded_max_force_N=float(recorded_force_n[recorded_cutting].max())
        if recorded_cutting.any() else 0.0,
        max_deviation=deviation,
        mismatched_ticks=int(n - same.sum()),
        final_bone_version=int(engine.grid.version),
        recorded_final_bone_version=int(rows["bone_version"][-1]) if n else None,
        overrides=overrides,
        complete=rec.complete,
        problems=list(rec.problems),
        stopped_reason=rec.stopped_reason,
        notes=notes,
        bone=bone,
        t_s=t_s,
        seq=rows["seq"].copy(),
        status=status,
        force=force,
        torque=torque,
        force_N=force_n,
        recorded_force_N=recorded_force_n,
        removed_mm3_tick=removed_tick,
        bone_version=version,
        out=out,
        shaft_out=shaft,
    )


def _max_abs(a: np.ndarray, b: np.ndarray) -> float:
    if a.size == 0:
        return 0.0
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))
    return float(np.nanmax(d)) if not np.isnan(d).all() else 0.0


def _bits(a: np.ndarray) -> np.ndarray:
    """float64 values as their bit patterns: equal bits are equal values, NaN included."""
    return np.ascontiguousarray(a, dtype=np.float64).view(np.int64)


def _materials(rec: Recording, us_scale: float, k: float | None,
               changes: Mapping[str | int, Mapping[str, Any]] | None,
               ) -> tuple[MaterialTable, dict[str, Any]]:
    """The recorded table with the overrides applied, and the overrides as JSON."""
    if isinstance(us_scale, bool) or not isinstance(us_scale, (int, float)) \
            or not math.isfinite(us_scale) or us_scale < 0.0:
        raise ValueError(f"us_scale must be a finite number ≥ 0, got {us_scale!r}")
    if k is not None and (isinstance(k, bool) or not isinstance(k, (int, float))
                          or not math.isfinite(k) or k < 0.0):
        raise ValueError(f"k must be a finite number ≥ 0, got {k!r}")
    try:
        recorded = {int(m["label"]): Material(str(m["name"]), m["us_n_mm2"], m["k"],
                                              m["forbidden"])
                    for m in rec.meta["materials"]}
        table = MaterialTable(recorded)
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(rec.path, f"the material table is not valid: {exc}") from None
    overrides: dict[str, Any] = {}
    if us_scale != 1.0:
        overrides["us_scale"] = us_scale
        for label, m in list(table):
            table.update(label, us_n_mm2=m.us_n_mm2 * us_scale)
    if k is not None:
        overrides["k"] = k
        for label, _ in list(table):
            table.update(label, k=float(k))
    for key, fields in (changes or {}).items():
        try:
            label = table.label_of(key) if isinstance(key, str) else int(key)
            material = table[label]
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"no material {key!r} in the recording (it has "
                             f"{', '.join(m.name for _, m in table)})") from None
        unknown = set(fields) - set(MATERIAL_FIELDS)
        if unknown:
            raise ValueError(f"material {material.name!r}: unknown fields "
                             f"{sorted(unknown)} (known: {', '.join(MATERIAL_FIELDS)})")
        table.update(label, **fields)
        overrides[f"material {material.name}"] = dict(fields)
    return table, overrides


def _engine(rec: Recording, bone: Bone, table: MaterialTable,
            ) -> tuple[BoneEngine, frames.Transform]:
    """The engine as the session had it at the start, and the session's frame transform."""
    meta = rec.meta
    try:
        shape = meta.get("grid_shape")
        if shape is not None and tuple(shape) != tuple(bone.grid.shape):
            raise RecordingError(rec.path, f"the snapshot's grid is {bone.grid.shape}, the "
                                           f"recording's {tuple(shape)}")
        params = CuttingParams.from_dict(meta["params"])
        shaft = ShaftParams(**meta["shaft"])
        burr = meta["burr"]
        engine = BoneEngine(bone.grid, table, params, shaft, n_theta=int(burr["n_theta"]),
                            n_phi=int(burr["n_phi"]), refine=int(burr["refine"]),
                            max_events=1 << 30)
        carve_from = meta.get("carve_from_g")
        engine.resume(None if carve_from is None else tuple(float(x) for x in carve_from),
                      frozenset(int(x) for x in meta.get("touching_labels", ())))
        if meta.get("burr_path") is not None:  # older recordings: the voxels alone
            engine.path.restore(meta["burr_path"])
        tf = frames.Transform(frames.frame(meta["frame"]),
                              tuple(meta.get("placement_position", (0.0, 0.0, 0.0))),
                              tuple(meta.get("placement_orientation", (0.0, 0.0, 0.0, 1.0))),
                              bone.grid.direction, bone.grid.origin_mm)
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(rec.path, f"meta.json cannot rebuild the engine: {exc}") from None
    return engine, tf

