"""An independent, converged integration of the model against a flat bone half-space.

It shares nothing with the numba kernels but the formulas of model.md: for each longitude φ the
set of latitudes θ that lie in bone and face the feed is found exactly (both conditions are
sinusoids in θ, so their boundaries are closed-form), the smooth integrand is integrated over
those θ-intervals by high-order Gauss–Legendre, and the result is integrated over φ by
SciPy's adaptive vector quadrature. No element fractions, no grid: it is the continuum integral
to ~1e-9 relative, the yardstick for the discretized model. Forces, torques and spin velocities
are formed in the world frame with cross products, independently of the kernels' algebra.

Valid for depths of cut from ~1e-4 mm up: for a burr that barely touches, the adaptive
quadrature can miss the sliver of longitudes where bone is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise
from typing import NamedTuple

import numpy as np

from .cases import CuttingCase
from .params import CuttingParams

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(48)


@dataclass(frozen=True)
class ReferenceResult:
    """Continuum values; vectors in the world frame. Units as in CuttingResult."""

    force_N: np.ndarray
    torque_Nmm: np.ndarray
    power_W: float
    removed_mm3_s: float
    mean_speed_m_s: float


def _basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Any right-handed orthonormal basis with e3 along the axis (the continuum is roll-free)."""
    e3 = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(e3[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(helper, e3)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e3, e1)
    return e1, e2, e3


class FlatFrame(NamedTuple):
    """A pose against a flat half-space, in the tool frame of ``_basis``.

    Attributes:
        e1, e2, e3: (3,) the basis, e3 along the axis.  v: (3,) the feed, mm/s.
        omega_vec: (3,) the spin Ω, rad/s (Ω = −ω·a for forward spin, params.spin_sign).
        s, v_tool: the unit outward surface normal and the feed (mm/s) on (e1, e2, e3).
        depth: s·(surface point − centre), mm: a point x of the burr is in bone where
            s·(x − centre) < depth.
    """

    e1: np.ndarray
    e2: np.ndarray
    e3: np.ndarray
    v: np.ndarray
    omega_vec: np.ndarray
    s: tuple[float, float, float]
    v_tool: tuple[float, float, float]
    depth: float


def flat_frame(params: CuttingParams, centre_mm: np.ndarray, axis: np.ndarray,
               feed_mm_s: np.ndarray, rpm: float, surface_point_mm: np.ndarray,
               surface_normal: np.ndarray) -> FlatFrame:
    """The references' common set-up of a pose (``centre_mm`` the burr's reference centre).
    ValueError if the spindle does not turn."""
    omega = params.spin_sign * rpm * 2.0 * math.pi / 60.0
    if omega == 0.0:
        raise ValueError("the reference needs a turning spindle")
    s = np.asarray(surface_normal, float) / np.linalg.norm(surface_normal)
    centre = np.asarray(centre_mm, float)
    v = np.asarray(feed_mm_s, float)
    e1, e2, e3 = _basis(np.asarray(axis, float))
    depth = float(s @ (np.asarray(surface_point_mm, float) - centre))
    return FlatFrame(e1, e2, e3, v, omega * e3,
                     (float(s @ e1), float(s @ e2), float(s @ e3)),
                     (float(v @ e1), float(v @ e2), float(v @ e3)), depth)


def result_from_totals(total: np.ndarray) -> ReferenceResult:
    """The result from integrated totals laid out as force (3, N), torque (3, N·mm), power
    (N·mm/s), removal rate (mm³/s), cut area (mm²), cut area × speed (mm²·mm/s)."""
    cut_area = float(total[8])
    return ReferenceResult(
        force_N=total[0:3],
        torque_Nmm=total[3:6],
        power_W=float(total[6]) * 1e-3,
        removed_mm3_s=float(total[7]),
        mean_speed_m_s=float(total[9]) / cut_area * 1e-3 if cut_area > 0 else 0.0,
    )


def _sinusoid_roots(p: float, q: float, level: float) -> list[float]:
    """θ ∈ (0, π) where p·sin θ + q·cos θ = level."""
    amp = math.hypot(p, q)
    if amp == 0.0 or abs(level) > amp:
        return []
    beta = math.atan2(p, q)  # p sin θ + q cos θ = amp·cos(θ − β)
    delta = math.acos(max(-1.0, min(1.0, level / amp)))
    roots = []
    for base in (beta + delta, beta - delta):
        for shift in (-2.0 * math.pi, 0.0, 2.0 * math.pi):
            t = base + shift
            if 0.0 < t < math.pi:
                roots.append(t)
    return roots


def reference_flat(
    params: CuttingParams,
    centre_mm: np.ndarray,
    axis: np.ndarray,
    feed_mm_s: np.ndarray,
    rpm: float,
    surface_point_mm: np.ndarray = np.zeros(3),  # noqa: B008 - read only
    surface_normal: np.ndarray = np.array([0.0, 0.0, 1.0]),  # noqa: B008 - read only
    epsrel: float = 1e-10,
) -> ReferenceResult:
    """Converged model values for a burr against the half-space behind ``surface_normal``."""
    radius = params.radius_mm
    f = flat_frame(params, centre_mm, axis, feed_mm_s, rpm, surface_point_mm, surface_normal)
    e1, e2, e3, v, omega_vec = f.e1, f.e2, f.e3, f.v, f.omega_vec
    s1, s2, s3 = f.s
    v1, v2, v3 = f.v_tool
    level = f.depth / radius  # s·n < level
    k = params.k

    def at_phi(phi: float) -> np.ndarray:
        cp, sp = math.cos(phi), math.sin(phi)
        su, vu = s1 * cp + s2 * sp, v1 * cp + v2 * sp
        cuts = sorted({0.0, math.pi, *_sinusoid_roots(su, s3, level),
                       *_sinusoid_roots(vu, v3, 0.0)})
        total = np.zeros(12)
        for lo, hi in pairwise(cuts):
            if hi - lo < 1e-15:
                continue
            mid = 0.5 * (lo + hi)
            in_bone = math.sin(mid) * su + math.cos(mid) * s3 < level
            facing = math.sin(mid) * vu + math.cos(mid) * v3 > 0.0
            if not (in_bone and facing):
                continue
            th = 0.5 * (hi - lo) * _GL_NODES + mid
            wt = 0.5 * (hi - lo) * _GL_WEIGHTS  # dθ weights; dA = R²·sin θ·dθ·dφ
            st, ct = np.sin(th), np.cos(th)
            # World-frame vectors and cross products, written from model.md afresh rather
            # than in the kernels' tool-frame algebra, so a sign slip in either shows.
            normals = np.outer(st * cp, e1) + np.outer(st * sp, e2) + np.outer(ct, e3)
            v_t = np.cross(omega_vec, radius * normals)  # spin velocity of each point
            speed = np.linalg.norm(v_t, axis=1)  # = |ω|·R·sin θ
            swept = radius * radius * st * wt * (normals @ v)  # dA·(n·v_f), mm³/s per dφ
            ft = params.us_n_mm2 * swept / speed  # |Ft| = Us·dA·(n·v_f)/|v_t|
            forces = -ft[:, None] * (v_t / speed[:, None]) - k * ft[:, None] * normals
            total[0:3] += forces.sum(axis=0)
            total[3:6] += np.cross(radius * normals, forces).sum(axis=0)
            total[6] += float(ft @ speed)
            total[7] += float(swept.sum())
            area = radius * radius * st * wt
            total[8] += float(area.sum())
            total[9] += float(area @ speed)
        return total

    # Here, not at the top: scipy.integrate takes ~0.7 s to import, and every `burrforce`
    # command builds its parser through the bench that imports this module.
    from scipy.integrate import quad_vec

    total, _err = quad_vec(at_phi, 0.0, 2.0 * math.pi, epsrel=epsrel, epsabs=1e-13, limit=20000)
    return result_from_totals(total)


def reference_case(case: CuttingCase, params: CuttingParams) -> ReferenceResult:
    """The converged reference for one of the thesis's cases (radius from ``params``)."""
    if params.radius_mm != case.radius_mm:
        raise ValueError(
            f"case radius {case.radius_mm} mm differs from params radius {params.radius_mm} mm"
        )
    return reference_flat(params, case.centre_mm, case.axis, case.feed_velocity_mm_s, case.rpm)


def plunge_removal_mm3_s(radius_mm: float, depth_mm: float, feed_mm_s: float) -> float:
    """Removal rate of a burr plunging straight into a flat surface, ``depth_mm`` deep, at
    ``feed_mm_s``: every element of the cut cap faces the feed, so it sweeps the cap's
    projected disc, v·π·(2Rh − h²) (mm³/s); beyond h = R the burr's equatorial disc, v·π·R²."""
    h = min(max(depth_mm, 0.0), radius_mm)
    return feed_mm_s * math.pi * (2.0 * radius_mm * h - h * h)
