"""Any burr shape (a surface of revolution) discretized in (s, φ), and its flat-workpiece model.

Element (j, k) covers arc length s ∈ [s_j, s_j + ds_j] along the profile (tip → top) and
φ ∈ [k·dφ, (k+1)·dφ] around the tool axis. On a surface of revolution dA = ρ·ds·dφ and the spin
speed is |v_t| = ω·ρ, so the model's cancelled weight dA/|v_t| = ds·dφ/ω never divides by the
vanishing speed near the axis, flat end discs included (there s runs along the radius:
dA = ρ·dρ·dφ). It is the sphere's R·dθ·dφ/ω (burr.py) for any profile (model.md, "Burr shapes").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .burr import DEFAULT_REFINE
from .kernels import new_buffer, new_scratch
from .kernels_revolved import cut_flat_revolved
from .params import CuttingParams
from .pose import check_pose
from .result import CuttingResult, result_from_out
from .shapes import Burr, Line
from .workpiece import FlatWorkpiece

#: Default element count: the sphere's default grid (24 × 48) has the same count; measured
#: (tests/test_model_shapes.py, docs/model.md "Burr shapes") to stay within 0.5 % of each
#: shape's converged reference on the thesis's nine cases.
DEFAULT_ELEMENTS = 1152

_COLUMNS = ("rho", "z", "n_rho", "n_z", "t_rho", "t_z", "kappa")
#: Gauss–Legendre nodes on [−1, 1] for the elements' moments (exact to rounding on an element).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)


@dataclass(frozen=True, eq=False)
class RevolvedGrid:
    """(s, φ) tables of one burr shape at one resolution. Immutable; shared between evaluations.

    Attributes:
        n_s, n_phi: elements along the profile and around the axis (n_phi a multiple of 4).
        elem: shape (7, n_s): ρ (mm), z (mm), outward normal (n_ρ, n_z), unit tangent
            (t_ρ, t_z, tip → top) and curvature κ (1/mm) at the element midpoints.
        ds: shape (n_s,), element lengths along the profile, mm.
        sub: shape (7, n_s, refine), the same columns at the sub-element midpoints.
        ds_sub: shape (n_s,), sub-element lengths, mm (ds / refine).
        cos_phi, sin_phi: shape (n_phi,), at the sector midpoints; d_phi: rad.
        cos_sub_p, sin_sub_p: shape (refine,), φ-offsets of the sub-element centres.
        segments: shape (n_seg, 6), the exact profile for the kernel's reach test: a line
            as (0, ρ0, z0, ρ1, z1, 0), an arc as (1, ρc, zc, r, ψ0, ψ1) (mm, rad).
        moments: shape (2, n_s), ∫ρ·n_ρ ds and ∫ρ·n_z ds over each element, mm² (exact on
            the profile): the removal rate's own integral along s, which the midpoint ρ·n·ds
            misses by ds²/24·(ρ·n)'' per element, a bias where ρ·n curves (a pole, a rim).
    """

    n_s: int
    n_phi: int
    refine: int
    elem: np.ndarray
    ds: np.ndarray
    sub: np.ndarray
    ds_sub: np.ndarray
    cos_phi: np.ndarray
    sin_phi: np.ndarray
    d_phi: float
    cos_sub_p: np.ndarray
    sin_sub_p: np.ndarray
    segments: np.ndarray
    moments: np.ndarray

    @property
    def n_elements(self) -> int:
        return self.n_s * self.n_phi

    @classmethod
    def build(cls, burr: Burr, n_elements: int = DEFAULT_ELEMENTS,
              refine: int = DEFAULT_REFINE) -> RevolvedGrid:
        """Tables with about ``n_elements`` near-square elements at the widest ring: element
        size h = √(L·2πρ_max/N) for a profile of length L, each segment getting
        max(1, round(length/h)) elements along s."""
        for name, n in (("n_elements", n_elements), ("refine", refine)):
            if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
                raise TypeError(f"{name} must be an integer, got {type(n).__name__}")
        if not 8 <= n_elements <= 4_000_000 or not 1 <= refine <= 16:
            raise ValueError(f"burr resolution out of range: n_elements={n_elements} "
                             f"(8..4000000), refine={refine} (1..16)")
        shape = burr.shape
        profile = shape.profile()
        total = sum(seg.length_mm for seg in profile)
        h = math.sqrt(total * 2.0 * math.pi * shape.max_radius_mm / n_elements)
        n_phi = max(4, 4 * round(2.0 * math.pi * shape.max_radius_mm / h / 4.0))
        elem_cols, sub_cols, ds, ds_sub, moments = [], [], [], [], []
        sub_u = (np.arange(refine) + 0.5) / refine
        for seg in profile:
            n = max(1, round(seg.length_mm / h))
            u0 = np.arange(n) / n
            elem_cols.append(np.array(seg.at(u0 + 0.5 / n)))
            sub_cols.append(np.array(seg.at(u0[:, None] + sub_u[None, :] / n)))
            ds.append(np.full(n, seg.length_mm / n))
            ds_sub.append(np.full(n, seg.length_mm / n / refine))
            # ρ·n is a trigonometric polynomial along an arc, a quadratic along a line.
            rho, _z, n_rho, n_z = seg.at(u0[:, None] + (_GL_X[None, :] + 1.0) / (2.0 * n))[:4]
            half = 0.5 * seg.length_mm / n
            moments.append(np.array([(rho * n_rho) @ _GL_W, (rho * n_z) @ _GL_W]) * half)
        d_phi = 2.0 * math.pi / n_phi
        phi = (np.arange(n_phi) + 0.5) * d_phi
        sub_p = ((np.arange(refine) + 0.5) / refine - 0.5) * d_phi
        segments = [(0.0, seg.rho0, seg.z0, seg.rho1, seg.z1, 0.0) if isinstance(seg, Line)
                    else (1.0, seg.rho_c, seg.z_c, seg.r, seg.psi0, seg.psi1) for seg in profile]
        tables = [np.concatenate(elem_cols, axis=1), np.concatenate(ds),
                  np.concatenate(sub_cols, axis=1), np.concatenate(ds_sub),
                  np.cos(phi), np.sin(phi), np.cos(sub_p), np.sin(sub_p), np.array(segments),
                  np.concatenate(moments, axis=1)]
        tables = [np.ascontiguousarray(t, dtype=np.float64) for t in tables]
        for t in tables:
            t.flags.writeable = False
        elem, ds_all, sub, ds_sub_all, cp, sp, csp, ssp, seg_table, moment_table = tables
        return cls(int(elem.shape[1]), int(n_phi), int(refine), elem, ds_all, sub, ds_sub_all,
                   cp, sp, d_phi, csp, ssp, seg_table, moment_table)


class RevolvedModel:
    """The cutting force of one burr of any shape against a flat workpiece (the thesis's).

    Owns the grid and preallocated buffers, like ``cutting.CuttingModel`` (which hands a shaped
    burr on a flat workpiece to this class); the
    ``params`` give Us, K, the spin and the minimum cutting speed (their ``radius_mm`` is not
    used: the shape has its own sizes). Positions are the burr's reference centre.
    """

    def __init__(self, burr: Burr, params: CuttingParams | None = None,
                 workpiece: FlatWorkpiece | None = None, n_elements: int = DEFAULT_ELEMENTS,
                 refine: int = DEFAULT_REFINE) -> None:
        self.burr = burr
        self.params = params if params is not None else CuttingParams()
        self.workpiece = workpiece if workpiece is not None else FlatWorkpiece()
        self.grid = RevolvedGrid.build(burr, n_elements, refine)
        self.normal_ratio, self.edge_ratio = burr.cutter.force_ratios(self.params.k)
        self._scratch = new_scratch()
        self._out = new_buffer()

    def evaluate_raw(self, centre_mm: np.ndarray, axis: np.ndarray, feed_mm_s: np.ndarray,
                     rpm: float) -> np.ndarray:
        """The kernel's (N_OUT,) result vector (kernels.OUT_*), reused between calls."""
        p, g, w = self.params, self.grid, self.workpiece
        omega = p.spin_sign * rpm * 2.0 * math.pi / 60.0
        cut_flat_revolved(g.elem, g.ds, g.sub, g.ds_sub, g.cos_phi, g.sin_phi, g.d_phi,
                          g.cos_sub_p, g.sin_sub_p, g.segments, g.moments, centre_mm, axis,
                          feed_mm_s, omega, p.us_n_mm2, self.normal_ratio, self.edge_ratio,
                          abs(rpm) >= p.min_cutting_rpm, w.surface_point_mm, w.surface_normal,
                          self._scratch, self._out)
        return self._out

    def evaluate(self, centre_mm: object, axis: object, feed_mm_s: object,
                 rpm: float) -> CuttingResult:
        """As ``CuttingModel.evaluate``, ``centre_mm`` the reference centre."""
        return result_from_out(self.evaluate_raw(*check_pose(centre_mm, axis, feed_mm_s, rpm)))
