"""The bone engine: a voxel bone being cut by one burr, tick by tick."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..hot_kernel import DirectCall
from ..model.burr import DEFAULT_N_THETA, BurrGrid
from ..model.kernels import (
    ACC_JACOBIAN,
    OUT_FORCE,
    OUT_SURFACE_NORMAL,
    OUT_TORQUE,
    new_buffer,
    new_scratch,
)
from ..model.params import CuttingParams
from ..model.pose import RPM_TO_RAD_S, check_pose
from ..model.result import CuttingResult, result_from_out
from ..model.shapes import Abrasive, Burr, Fluted, Sphere
from .bricks import BRICK, LABEL_WORDS, forbidden_bricks, forbidden_from_labels
from .carve import N_TOUCH, TOUCH_FORBIDDEN
from .carve_revolved import bounding_radius_mm
from .grid import BoneGrid, check_voxel_size
from .history import BurrPath
from .materials import N_LABELS, MaterialTable
from .seqlock import header_address, read_version, write_begin, write_end
from .shaft import N_SHAFT, SHAFT_DEPTH, SHAFT_FORCE, SHAFT_TORQUE, SHAFT_VOLUME
from .tally import CarveTally, ForbiddenContact
from .tick import bone_tick, removed_mm3
from .tick_tables import RevolvedTables, RevolvedTick, SphereTick
from .voxels import coverage_cache_shape

#: Elements the bone's surface crosses are integrated on refine × refine sub-elements. With
#: voxels 2 × 2 is as accurate as 3 × 3 (`burrforce bench accuracy`: 0.54 % against 0.53 %
#: worst case at 0.1 mm, 1152 elements) and 15 % faster: the density ramp is already smooth.
VOXEL_REFINE = 2
#: 16 M entries (128 MB) — a burr 100 voxels across.
MAX_CACHE_ENTRIES = 1 << 24

_kernels_loaded = False
#: The tick kernels this process has run (``warm_up``), by burr family: False for the round
#: abrasive burr's (``SphereTick``), True for every other burr's (``RevolvedTick``).
_warmed_ticks: set[bool] = set()
#: The stand-in burr ``warm_up`` compiles the revolved tick with (any non-round-abrasive one).
_WARM_CUTTER = Fluted(n_flutes=6)
#: What ``step_raw`` checks of its vectors before the direct call: float64, contiguous.
_F64 = np.dtype(np.float64)
_VEC_STRIDES = (8,)


def load_kernels() -> None:
    """Load (or compile) the kernels an engine runs besides its tick — both forbidden-brick
    scans and a shared bone's seqlock writes — on tiny arrays, once per process. The first
    engine does it: the hot loop builds that one before any session streams, so no later
    build holds the GIL for milliseconds loading machine code while another session streams
    (measured: 16–22 ms holds when a shared bone's kernels were first loaded beside a
    streaming session)."""
    global _kernels_loaded
    if _kernels_loaded:
        return
    density = np.ones((BRICK, BRICK, BRICK), dtype=np.uint8)
    forbidden = np.zeros(N_LABELS, dtype=np.uint8)
    out = np.zeros((1, 1, 1), dtype=np.uint8)
    forbidden_bricks(density, density, forbidden, out)
    forbidden_from_labels(np.zeros((1, 1, 1, LABEL_WORDS), dtype=np.uint64), forbidden, out)
    header = np.zeros(8, dtype=np.int64)
    write_begin(header_address(header))
    write_end(header_address(header), 0)
    read_version(header)  # mapping a shared bone reads its version
    _kernels_loaded = True


@dataclass(frozen=True)
class ShaftParams:
    """The burr's shaft: a cylinder from the burr centre toward the handle.

    Attributes:
        radius_mm: shaft radius, mm (must be below the burr radius). Default 1.0 (a 2 mm
            neck, typical of 4–6 mm surgical burrs).
        length_mm: how much of it is checked for contact, mm; 0 turns shaft contact off.
        stiffness_n_mm3: contact stiffness, N per mm³ of bone overlapping the shaft. A
            rendering parameter, not a measured property: the default 10 N/mm³ pushes back
            with ≈ 3 N when 5 mm of a 1 mm-radius shaft lies 0.1 mm deep in bone.
    """

    radius_mm: float = 1.0
    length_mm: float = 15.0
    stiffness_n_mm3: float = 10.0

    def __post_init__(self) -> None:
        for name, value, upper in (("radius_mm", self.radius_mm, 50.0),
                                   ("length_mm", self.length_mm, 500.0),
                                   ("stiffness_n_mm3", self.stiffness_n_mm3, 1e6)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not 0.0 <= value <= upper:
                raise ValueError(f"shaft {name} must be a number in [0, {upper:g}], "
                                 f"got {value!r}")


def check_burr(spacing_mm: np.ndarray, params: CuttingParams, shaft: ShaftParams) -> None:
    """The burr must span several voxels, and a shaft that is checked must be thinner than
    the burr. ValueError says which is wrong."""
    check_voxel_size(np.asarray(spacing_mm, dtype=np.float64), params.radius_mm)
    if shaft.length_mm > 0 and shaft.radius_mm >= params.radius_mm:
        raise ValueError(f"the shaft radius {shaft.radius_mm} mm must be smaller than the burr "
                         f"radius {params.radius_mm} mm (set shaft_radius_mm below it, in the "
                         f"same request as the burr)")


@dataclass(frozen=True)
class BoneTickResult:
    """One tick. Vectors are float64 arrays of shape (3,) in the world frame.

    Attributes:
        cut: the cutting force and its companions (``model.CuttingResult``).
        removed_mm3: bone volume removed this tick, mm³.
        removed_mm3_by_material: the same per material name (only materials that lost bone).
        shaft_force_N, shaft_torque_Nmm: contact of the shaft with bone (torque about the burr
            centre). Not part of ``cut``: the shaft does not cut.
        shaft_overlap_mm3: bone volume inside the shaft, mm³.
        shaft_contact: the shaft touches bone.
        forbidden_contact: the burr overlaps a forbidden structure this tick.
        forbidden_label: label of the most-covered forbidden voxel (0 if none).
        bone_version: the bone's version after this tick.
    """

    cut: CuttingResult
    removed_mm3: float
    removed_mm3_by_material: dict[str, float]
    shaft_force_N: np.ndarray
    shaft_torque_Nmm: np.ndarray
    shaft_overlap_mm3: float
    shaft_contact: bool
    forbidden_contact: bool
    forbidden_label: int
    bone_version: int


class BoneEngine:
    """A voxel bone cut by one burr: carving, cutting force and shaft contact.

    Each :meth:`step` is one numba call that sweeps the burr's neighbourhood (partial volume),
    evaluates the model's force from the voxels, and checks the shaft. Per-material Us and K
    come from ``materials``; ``params`` supplies the burr radius, spin direction and minimum
    cutting speed (its own ``us_n_mm2``/``k`` are not used: materials own them), and the
    burr's shape (``params.shape``; :meth:`set_burr` changes it between ticks). Every burr
    runs ``tick.bone_tick``: the round abrasive one on its ``BurrGrid``, any other on a
    ``RevolvedGrid`` (``tick_tables.RevolvedTick``) with about as many elements.

    Args:
        grid: the bone (carved in place).
        materials: label → material. Default: label 1 is the thesis's cortical bone.
        params: burr and spindle parameters.
        shaft: shaft geometry; ``ShaftParams(length_mm=0)`` turns it off.
        n_theta, n_phi, refine: burr resolution (see ``BurrGrid``).
        max_events: forbidden-contact events kept (oldest dropped first) in a private tally.
        tally: where the removed volume and the forbidden contacts are counted (``tally``):
            a shared bone's own, so that they survive the engine; default a private one.
    """

    def __init__(
        self,
        grid: BoneGrid,
        materials: MaterialTable | None = None,
        params: CuttingParams | None = None,
        shaft: ShaftParams | None = None,
        n_theta: int = DEFAULT_N_THETA,
        n_phi: int | None = None,
        refine: int = VOXEL_REFINE,
        max_events: int = 10_000,
        tally: CarveTally | None = None,
    ) -> None:
        load_kernels()
        self.grid = grid
        self.materials = materials if materials is not None else MaterialTable()
        self.shaft = shaft if shaft is not None else ShaftParams()
        #: Where the burr last carved (grid frame), NaN when unknown: carving skips what that
        #: position already swept.
        self._previous = np.full(3, np.nan)
        #: The path the burr carved along: availability that knows what it already cut.
        spacing = np.asarray(grid.spacing_mm, dtype=np.float64)
        self.path = BurrPath((-0.5 * spacing, (np.asarray(grid.shape) - 0.5) * spacing),
                             carved_before=bool(grid.swept.any()))
        #: Tables of the current burr when it is not the round abrasive one, else None.
        self._revolved: RevolvedTables | None = None
        self.burr = BurrGrid.build(n_theta, n_phi, refine)
        self.params = params if params is not None else CuttingParams()
        self._vert = np.empty((self.burr.n_theta + 1, self.burr.n_phi, 3))
        self._acc = new_scratch()
        self.out = new_buffer()
        #: ∂F/∂v_f of the last tick's cut, float64 (9,) row-major, grid frame, N·s/mm: the
        #: force is exactly ``jacobian @ feed`` over the elements that cut (a view).
        self.jacobian = self._acc[ACC_JACOBIAN:ACC_JACOBIAN + 9]
        self.shaft_out = np.zeros(N_SHAFT)
        self.touch = np.zeros(N_TOUCH)
        self._touched = np.zeros((N_LABELS, 4))
        self._removed_tick = np.zeros(N_LABELS)
        #: Removal since the bone was loaded and the forbidden contacts begun: they outlive
        #: this engine when the tally is the shared bone's.
        self.tally = tally if tally is not None else CarveTally.private(max_events)
        self._removed_total = self.tally.removed
        self._touching: frozenset[int] = frozenset()
        self.ticks = 0
        #: Stamps the coverage cache: one per kernel call, never reused.
        self._stamp = 0
        self._brick_forbidden = np.zeros(grid.brick_bone.shape, dtype=np.uint8)
        #: The material table (and its forbidden flags' revision) ``_brick_forbidden`` is for.
        self._forbidden_of: MaterialTable | None = None
        self._forbidden_revision = -1
        #: The round burr's tick bound to this engine's tables and buffers (``_bind_tick``).
        self._bound: DirectCall | None = None
        #: The shared header the seqlock last wrote, and its address (``seqlock``).
        self._header: np.ndarray | None = None
        self._header_at = 0
        # Now, not in the first tick: a warm-up must not scan the bone.
        self.refresh_forbidden()

    @property
    def params(self) -> CuttingParams:
        return self._params

    @params.setter
    def params(self, params: CuttingParams) -> None:
        check_burr(self.grid.spacing_mm, params, self.shaft)
        burr = params.shape
        revolved = RevolvedTables.build(burr, params.k, self.burr.n_theta * self.burr.n_phi,
                                        self.burr.refine) if _revolved_tick(params) else None
        reach = params.radius_mm if revolved is None else bounding_radius_mm(burr)
        shape = coverage_cache_shape(reach, self.grid.spacing_mm)
        if math.prod(shape) > MAX_CACHE_ENTRIES:
            shape = (1, 1, 1)  # voxels far finer than the burr: compute every coverage
        carved_unknown = self._revolved is not None
        self._params = params
        # What ``step_raw`` reads of them every tick, kept here: a property costs ~50 ns.
        self._rad_s_per_rpm = params.spin_sign * RPM_TO_RAD_S
        self._min_cutting_rpm = params.min_cutting_rpm
        self._revolved = revolved
        # Entries are stamped with the call that wrote them (stamps count from 1).
        self._cache = np.zeros(shape, dtype=np.int64)
        # The revolved carve's per-row reach, over the same neighbourhood (carve_revolved).
        self._rows = np.zeros((shape[0], shape[1], 3), dtype=np.int64)
        if carved_unknown:
            # Another shape's cuts are not capsules of the path: it no longer knows them all.
            self.forget_path()
        else:
            self.forget_last_carve()

    @property
    def contact_radius_mm(self) -> float:
        """The radius of the sphere with the burr's surface area, mm: what a contact area
        is compared with (the coupled output's "wholly in bone" share and cap depth). The
        radius itself for a round burr."""
        rv = self._revolved
        if rv is None:
            return self._params.radius_mm
        area_mm2 = 2.0 * math.pi * float(np.dot(rv.grid.elem[0], rv.grid.ds))
        return math.sqrt(area_mm2 / (4.0 * math.pi))

    @property
    def burr_shape(self) -> Burr:
        """The burr cutting now (``params.shape``: a round abrasive burr of
        ``params.radius_mm`` unless :meth:`set_burr` chose another)."""
        return self._params.shape

    def set_burr(self, burr: Burr) -> None:
        """Change the burr between ticks (a tool change mid-stream): its shape, size and
        cutter. ``params.radius_mm`` becomes the shape's largest radius (the sphere's radius);
        the coverage cache follows and the next tick carves the whole neighbourhood.
        ValueError (engine unchanged) if the voxels are too coarse for it or the shaft is not
        thinner than it."""
        if not isinstance(burr, Burr):
            raise TypeError(f"burr must be a shapes.Burr, got {type(burr).__name__}")
        if burr != self.burr_shape:
            self.params = self._params.with_(burr=burr)

    def set_materials(self, materials: MaterialTable,
                      brick_forbidden: np.ndarray | None = None) -> None:
        """Use another material table. Its forbidden flags need a scan of the grid only if
        they differ from the current table's; a caller can do that scan beforehand (outside
        any lock: ``forbidden_bricks`` releases the GIL) and pass the result."""
        if brick_forbidden is not None:
            self._brick_forbidden = brick_forbidden
        elif not np.array_equal(materials.forbidden, self.materials.forbidden):
            self.materials = materials
            self.refresh_forbidden()
            return
        self.materials = materials
        self._forbidden_of = materials
        self._forbidden_revision = materials.forbidden_revision

    def refresh_forbidden(self) -> None:
        """Recompute which bricks hold forbidden structures (done automatically when the
        material table's forbidden flags change, or call it after writing ``grid.labels``;
        a grid with a brick label mask needs that recounted first: ``bricks.brick_labels``)."""
        self.forbidden_bricks_for(self.materials, self._brick_forbidden)
        self._forbidden_of = self.materials
        self._forbidden_revision = self.materials.forbidden_revision

    def forbidden_bricks_for(self, materials: MaterialTable,
                             out: np.ndarray | None = None) -> np.ndarray:
        """Which bricks hold a structure ``materials`` calls forbidden (uint8, brick shape),
        without changing the engine. From the grid's brick label mask when it has one (a
        shared bone's: a pass over the bricks), else a scan of the voxels; either kernel
        releases the GIL."""
        g = self.grid
        if out is None:
            out = np.zeros(g.brick_bone.shape, dtype=np.uint8)
        if g.brick_labels is not None:
            forbidden_from_labels(g.brick_labels, materials.forbidden, out)
        else:
            forbidden_bricks(g.density, g.labels, materials.forbidden, out)
        return out

    @property
    def last_carve_g_mm(self) -> tuple[float, float, float] | None:
        """Where the burr's centre last carved (grid frame, mm), or None when the next tick
        carves the whole neighbourhood: a recording saves it so its replay skips what the
        live engine skipped."""
        if np.isnan(self._previous).any():
            return None
        return (float(self._previous[0]), float(self._previous[1]), float(self._previous[2]))

    @property
    def touching(self) -> frozenset[int]:
        """The labels of the forbidden materials the burr touches now."""
        return self._touching

    def resume(self, last_carve_g_mm: tuple[float, float, float] | None,
               touching: frozenset[int]) -> None:
        """Take up where an engine left off (:attr:`last_carve_g_mm`, :attr:`touching`): a
        replay starts from the state its recording saved, so it carves and reports contact
        events as the live engine did."""
        self._previous[:] = np.nan if last_carve_g_mm is None else last_carve_g_mm
        self._touching = frozenset(int(x) for x in touching)

    def forget_last_carve(self) -> None:
        """Carve the burr's whole neighbourhood next tick (after the radius or the bone's
        ``swept`` array changed behind the engine's back)."""
        self._previous[:] = np.nan
        self.path.break_run()

    def forget_path(self) -> None:
        """The bone's ``swept`` voxels changed behind the engine's back (not by its own
        carving): the path no longer describes every cut, so the voxels' availability is
        consulted everywhere again."""
        self.path.clear(carved_before=True)
        self.forget_last_carve()

    # -- resolution -------------------------------------------------------------------------
    def set_resolution(self, n_theta: int, n_phi: int | None = None,
                       refine: int = VOXEL_REFINE) -> None:
        wanted = (n_theta, 2 * n_theta if n_phi is None else n_phi, refine)
        if wanted != self.burr.key:
            self.burr = BurrGrid.build(n_theta, n_phi, refine)
            self._vert = np.empty((self.burr.n_theta + 1, self.burr.n_phi, 3))
            if self._revolved is not None:
                self._revolved = RevolvedTables.build(
                    self._revolved.burr, self._params.k, self.burr.n_theta * self.burr.n_phi,
                    self.burr.refine)

    # -- ticks ------------------------------------------------------------------------------
    def step_raw(self, centre_g: np.ndarray, axis_g: np.ndarray, feed_g: np.ndarray,
                 rpm: float, carve: bool = True) -> bool:
        """Fast path, grid frame: fills ``out`` (model.kernels.OUT_*), ``shaft_out``
        (shaft.SHAFT_*) and ``touch`` (carve.TOUCH_*), and returns True if bone was removed.

        Inputs must be validated float64 (3,) arrays already in the grid frame, ``axis_g`` of
        unit length; forbidden-contact events are not recorded here (see :meth:`step`).
        """
        p = self._params
        b = self.burr
        g = self.grid
        m = self.materials
        if m is not self._forbidden_of or m.forbidden_revision != self._forbidden_revision:
            self.refresh_forbidden()
        omega = rpm * self._rad_s_per_rpm
        cutting = abs(rpm) >= self._min_cutting_rpm
        self._stamp += 1
        shared = g.shared_header
        if shared is not None and carve:
            if shared is not self._header:
                self._header, self._header_at = shared, header_address(shared)
            write_begin(self._header_at)  # odd: voxels being written (SharedBone reads around)
        # A tick that raises (an INTERNAL reply) must still close the seqlock, under a new
        # version: readers of the shared bone would otherwise wait on an odd counter for good,
        # and bricks it changed would be missing from deltas since the old version.
        try:
            bound = self._bound
            if bound is None:
                bound = self._bind_tick()
            # As _owners(), compared by identity, not by value; spelled out because a loop
            # over the pairs costs about 1 µs a tick.
            o = bound.owners
            if (o[0] is not b or o[1] is not p or o[2] is not self.shaft or o[3] is not m
                    or o[4] is not self._brick_forbidden or o[5] is not self.path
                    or o[6] is not self._revolved or o[7] is not self._rows):
                bound = self._bind_tick()
            if (centre_g.dtype is _F64 and axis_g.dtype is _F64 and feed_g.dtype is _F64
                    and centre_g.strides == _VEC_STRIDES and axis_g.strides == _VEC_STRIDES
                    and feed_g.strides == _VEC_STRIDES):
                removed = bound.call(centre_g, axis_g, feed_g, omega, cutting, carve,
                                     g.version + 1, self._stamp)
            else:  # not the bound types: numba's dispatch (and a compile) sorts it out
                removed = bone_tick(*bound.fixed, centre_g, axis_g, feed_g, omega, cutting,
                                    carve, g.version + 1, self._stamp)
            if removed:
                g.version += 1
        except BaseException:
            if carve:  # it may have stamped bricks with the next version before it raised
                g.version += 1
            raise
        finally:
            if shared is not None and carve:
                write_end(self._header_at, g.version)
        self.ticks += 1
        return removed

    def _owners(self) -> tuple:
        """The objects the bound tick's fixed arguments come from (``_bind_tick``)."""
        return (self.burr, self._params, self.shaft, self.materials, self._brick_forbidden,
                self.path, self._revolved, self._rows)

    def _bind_tick(self) -> DirectCall:
        """Bind the tick to this engine's tables and buffers (``DirectCall``), for the round
        abrasive burr or any other alike: again whenever one of the objects they come from is
        replaced (the burr grid, the params and their coverage cache, the shaft, the
        materials, the forbidden bricks, the path, the other burr's tables and its carve's
        row table). The grid's arrays
        are bound for the engine's life: write into them, never rebind them."""
        fixed = self._tick_fixed(self._revolved)
        # The tail's types: what step_raw checks before each direct call.
        tail = (np.zeros(3), np.zeros(3), np.zeros(3), 0.0, True, True, 0, 0)
        bound = DirectCall(bone_tick, fixed, tail, self._owners(), previous=self._bound)
        self._bound = bound
        return bound

    def _tick_fixed(self, rv: RevolvedTables | None) -> tuple:
        """``bone_tick``'s arguments up to ``centre``: the round burr's tables
        (``SphereTick``) if ``rv`` is None, else ``rv``'s (``RevolvedTick``), then the
        bone's, materials', shaft's and this engine's buffers."""
        g = self.grid
        m = self.materials
        if rv is None:
            b = self.burr
            path = self.path
            burr = SphereTick(b.cos_theta, b.sin_theta, b.cos_phi, b.sin_phi, b.d_theta,
                              b.d_phi, b.cos_sub_t, b.sin_sub_t, b.cos_sub_p, b.sin_sub_p,
                              b.cos_theta_v, b.sin_theta_v, b.cos_phi_v, b.sin_phi_v,
                              self._params.radius_mm, self._previous, path.ring, path.meta,
                              path.candidates)
            vert = self._vert
        else:
            r = rv.grid
            burr = RevolvedTick(r.elem, r.ds, r.sub, r.ds_sub, r.cos_phi, r.sin_phi, r.d_phi,
                                r.cos_sub_p, r.sin_sub_p, rv.corners, rv.cos_pv, rv.sin_pv,
                                rv.profile, rv.bounds, rv.geo, rv.normal_ratio, rv.edge_ratio,
                                rv.material_k, rv.shaft_base, self._rows)
            vert = rv.vert
        return (burr, g.density, g.swept, g.labels, m.us, m.usk, m.forbidden, g.brick_bone,
                g.brick_full, g.brick_version, self._brick_forbidden, g.spacing_mm,
                self.shaft.radius_mm, self.shaft.length_mm, self.shaft.stiffness_n_mm3,
                self._removed_tick, self._removed_total, self.touch, self._touched, vert,
                self._acc, self.out, self.shaft_out, self._cache)

    def step(
        self,
        centre_mm: np.ndarray | tuple[float, float, float],
        axis: np.ndarray | tuple[float, float, float],
        feed_mm_s: np.ndarray | tuple[float, float, float],
        rpm: float,
        time_s: float | None = None,
        carve: bool = True,
    ) -> BoneTickResult:
        """One tick in the world frame: carve where the burr is (if it spins fast enough and
        ``carve``), then the cutting force and the shaft's contact. Records a
        :class:`ForbiddenContact` event (at ``time_s``, default the monotonic clock) when the
        burr starts touching a forbidden structure.

        Raises:
            ValueError: non-finite or implausible inputs (as ``CuttingModel.evaluate``).
        """
        centre, ax, feed, rpm = check_pose(centre_mm, axis, feed_mm_s, rpm)
        if not isinstance(carve, (bool, np.bool_)):
            raise ValueError(f"carve must be true or false, got {carve!r}")
        if time_s is not None and not math.isfinite(time_s):
            raise ValueError(f"time_s must be finite, got {time_s!r}")
        g = self.grid
        ax = ax / np.linalg.norm(ax)
        self.step_raw(g.to_grid_point(centre), g.to_grid_vector(ax), g.to_grid_vector(feed),
                      rpm, carve)
        self.record_contact(time.monotonic() if time_s is None else float(time_s))
        out = self.out.copy()
        shaft = self.shaft_out.copy()
        if not g.identity_direction:
            for base in (OUT_FORCE, OUT_TORQUE, OUT_SURFACE_NORMAL):
                out[base:base + 3] = g.to_world_vector(out[base:base + 3])
            for base in (SHAFT_FORCE, SHAFT_TORQUE):
                shaft[base:base + 3] = g.to_world_vector(shaft[base:base + 3])
        by_label = {int(label): float(v) * self._mm3_per_unit
                    for label, v in enumerate(self._removed_tick) if v > 0.0}
        touched = self._touched[:, 0]
        return BoneTickResult(
            cut=result_from_out(out),
            removed_mm3=sum(by_label.values()),
            removed_mm3_by_material={self.materials.name_of(label): v
                                     for label, v in by_label.items()},
            shaft_force_N=shaft[SHAFT_FORCE:SHAFT_FORCE + 3].copy(),
            shaft_torque_Nmm=shaft[SHAFT_TORQUE:SHAFT_TORQUE + 3].copy(),
            shaft_overlap_mm3=float(shaft[SHAFT_VOLUME]),
            shaft_contact=bool(shaft[SHAFT_VOLUME] > 0.0 or shaft[SHAFT_DEPTH] > 0.0),
            forbidden_contact=bool(self.touch[TOUCH_FORBIDDEN] > 0.0),
            forbidden_label=int(np.argmax(touched)) if touched.any() else 0,
            bone_version=g.version,
        )

    def record_contact(self, now: float) -> None:
        """After :meth:`step_raw`: one event per forbidden label when contact with it begins
        (not every tick, and not again while it continues, whichever neighbour is the most
        covered). ``now`` is the event's time, s."""
        if self.touch[TOUCH_FORBIDDEN] <= 0.0:
            if self._touching:  # only when contact ends: no allocation on every packet
                self._touching = frozenset()
            return
        now_touching = frozenset(int(x) for x in np.flatnonzero(self._touched[:, 0]))
        for label in sorted(now_touching - self._touching):
            position = self.grid.to_world_point(self._touched[label, 1:4])
            self.tally.add_contact(now, tuple(float(x) for x in position),  # type: ignore
                                   label)
        self._touching = now_touching

    @property
    def events(self) -> list[ForbiddenContact]:
        """The forbidden contacts kept, oldest first (``tally.begun`` counts them all)."""
        return self.tally.latest(None, self.materials.name_of)

    # -- totals -----------------------------------------------------------------------------
    def removed_this_tick_mm3(self) -> float:
        """Bone the last tick removed, mm³ (all materials). Called on every cutting packet:
        one compiled call (numpy's sum and the grid's volume took ~3 µs of Python)."""
        return removed_mm3(self._removed_tick, self.grid.spacing_mm)

    @property
    def _mm3_per_unit(self) -> float:
        """mm³ per unit of the kernels' removal counters (density × swept steps)."""
        return self.grid.voxel_volume_mm3 / (255.0 * 255.0)

    def removed_mm3_by_material(self) -> dict[str, float]:
        """Bone removed since the bone was loaded, mm³ per material name (since the engine
        was made, with a private tally)."""
        return {self.materials.name_of(label): float(v) * self._mm3_per_unit
                for label, v in enumerate(self._removed_total) if v > 0.0}

    def removal_energy_J(self) -> float:
        """Σ Us(material) × removed volume since the engine was made, J (N·mm → mJ)."""
        return float(np.dot(self._removed_total, self.materials.us)) * self._mm3_per_unit * 1e-3

    def warm_up(self, every_burr: bool = True) -> None:
        """Compile (or load from numba's cache) every kernel a tick uses, without touching the
        bone: one tick far outside the grid. ``every_burr``: the other burr family's tick too
        (``tick_warmed``), else only this burr's."""
        far = np.full(3, -1e5)
        unit = np.array([0.0, 0.0, 1.0])
        self.step_raw(far, unit, unit, self.params.min_cutting_rpm + 1.0, carve=False)
        self.ticks -= 1
        self.removed_this_tick_mm3()  # run only by ticks that remove bone, which this is not
        _warmed_ticks.add(self._revolved is not None)
        if not every_burr:
            return
        # The other burrs' tick too (a tool change mid-stream must not compile): the round
        # one's, or a small stand-in's of the same types as any other's.
        other = None if self._revolved is not None else RevolvedTables.build(
            Burr(Sphere(self._params.radius_mm), _WARM_CUTTER), self._params.k, 8,
            self.burr.refine)
        self._stamp += 1
        bone_tick(*self._tick_fixed(other), far, unit, unit, 1.0, True, False,
                  self.grid.version + 1, self._stamp)
        _warmed_ticks.add(other is not None)


def tick_warmed(params: CuttingParams) -> bool:
    """Whether this process has run the tick ``params``' burr needs (``BoneEngine.warm_up``):
    if not, an engine's first tick with it would compile it, or load it from the cache."""
    return _revolved_tick(params) in _warmed_ticks


def _revolved_tick(params: CuttingParams) -> bool:
    """Whether ``params``' burr runs the revolved-profile tick: all but the round abrasive."""
    burr = params.shape
    return not (isinstance(burr.shape, Sphere) and isinstance(burr.cutter, Abrasive))

