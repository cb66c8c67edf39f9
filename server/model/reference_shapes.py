"""An independent, converged integration of the model for any burr shape on a flat half-space.

It shares nothing with the (s, φ) grid and its kernel but the formulas of model.md: on each ring
of the profile (fixed arc length s) the set of longitudes φ that lie in bone and face the feed
is exact (both conditions are sinusoids in φ), and every integrand on a ring is a trigonometric
polynomial of degree ≤ 3 in φ (forces of degree 2, torques x × F of degree 3), so it is sampled
at 8 longitudes, turned into its Fourier coefficients and integrated analytically over those
φ-intervals. The result is integrated along each profile segment by SciPy's adaptive vector
quadrature. Vectors are formed in the world frame with cross products, and a fluted cutter's
force is built from the rake face's normal and the chip-flow direction (Stabler's rule), not
from the closed-form ratios the kernel uses, so a slip in either shows.

Valid for depths of cut from ~1e-4 mm up (as reference.py).
"""

from __future__ import annotations

import math
from itertools import pairwise

import numpy as np

from .params import CuttingParams
from .reference import ReferenceResult, flat_frame, result_from_totals
from .shapes import Burr, Fluted

_N_SAMPLES = 8  # exact Fourier coefficients up to degree 3
_PHI_SAMPLES = 2.0 * math.pi * np.arange(_N_SAMPLES) / _N_SAMPLES
_DEGREES = np.arange(1, 4)
# Per ring: force (3), torque (3), power, removal rate, cut area, cut area × speed.
_N_OUT = 10


def _roots(a: float, b: float, level: float) -> list[float]:
    """φ ∈ [0, 2π) where a·cos φ + b·sin φ = level."""
    amp = math.hypot(a, b)
    if amp == 0.0 or abs(level) >= amp:
        return []
    beta = math.atan2(b, a)
    delta = math.acos(level / amp)
    return [(beta + sgn * delta) % (2.0 * math.pi) for sgn in (1.0, -1.0)]


def _fluted_direction(c_hat: np.ndarray, n: np.ndarray, edge: np.ndarray, rake: float,
                      friction: float) -> np.ndarray:
    """The force on the tool per unit cutting (tangential) force, shape (8, 3), from oblique
    cutting geometry: rake-face normal m̂ and chip flow k̂ at η = i (Stabler)."""
    sin_i = np.einsum("ij,ij->i", edge, c_hat)
    cos_i = np.sqrt(1.0 - sin_i ** 2)
    up = -n  # from the machined surface through the chip
    p = (c_hat - sin_i[:, None] * edge) / cos_i[:, None]  # in the surface, ⟂ the edge
    m_hat = math.cos(rake) * p + math.sin(rake) * up
    d_n = math.cos(rake) * up - math.sin(rake) * p
    k_hat = cos_i[:, None] * d_n - sin_i[:, None] * edge
    on_tool = -m_hat + math.tan(friction) * k_hat
    cutting = -np.einsum("ij,ij->i", on_tool, c_hat)
    return on_tool / cutting[:, None]


def reference_shape_flat(
    burr: Burr,
    params: CuttingParams,
    centre_mm: np.ndarray,
    axis: np.ndarray,
    feed_mm_s: np.ndarray,
    rpm: float,
    surface_point_mm: np.ndarray = np.zeros(3),  # noqa: B008 - read only
    surface_normal: np.ndarray = np.array([0.0, 0.0, 1.0]),  # noqa: B008 - read only
    epsrel: float = 1e-10,
) -> ReferenceResult:
    """Converged model values for ``burr`` (reference centre at ``centre_mm``) against the
    half-space behind ``surface_normal``. Us, K and the spin come from ``params``."""
    f = flat_frame(params, centre_mm, axis, feed_mm_s, rpm, surface_point_mm, surface_normal)
    e1, e2, e3, v, omega_vec = f.e1, f.e2, f.e3, f.v, f.omega_vec
    s1, s2, s3 = f.s
    v1, v2, v3 = f.v_tool
    level = f.depth  # in bone: s·x < level
    cutter = burr.cutter
    cp, sp = np.cos(_PHI_SAMPLES), np.sin(_PHI_SAMPLES)
    radial = np.outer(cp, e1) + np.outer(sp, e2)  # e_ρ at the samples, (8, 3)
    around = np.cross(e3, radial)  # φ̂

    def ring(seg, u: float) -> np.ndarray:
        rho, z, nr, nz, tr, tz, _k = (float(x) for x in seg.at(np.array(u)))
        if rho <= 0.0:
            return np.zeros(_N_OUT)
        # φ where the ring enters bone and where its normal turns to face the feed.
        in_a, in_b, in_level = rho * s1, rho * s2, level - z * s3
        if math.hypot(in_a, in_b) <= -in_level:
            return np.zeros(_N_OUT)  # the whole ring is out of bone
        cuts = sorted({0.0, 2.0 * math.pi, *_roots(in_a, in_b, in_level),
                       *_roots(nr * v1, nr * v2, -nz * v3)})
        intervals = []
        for lo, hi in pairwise(cuts):
            mid = 0.5 * (lo + hi)
            if hi - lo < 1e-15:
                continue
            in_bone = in_a * math.cos(mid) + in_b * math.sin(mid) < in_level
            facing = nr * (v1 * math.cos(mid) + v2 * math.sin(mid)) + nz * v3 > 0.0
            if in_bone and facing:
                intervals.append((lo, hi))
        if not intervals:
            return np.zeros(_N_OUT)
        x = rho * radial + z * e3
        n = nr * radial + nz * e3
        tangent = tr * radial + tz * e3
        v_t = np.cross(omega_vec, x)
        speed = np.linalg.norm(v_t, axis=1)  # = |ω|·ρ
        c_hat = v_t / speed[:, None]
        swept = rho * (n @ v)  # dA·(n·v_f) per ds·dφ, mm³/s
        ft = params.us_n_mm2 * swept / speed
        if isinstance(cutter, Fluted):
            beta = math.radians(cutter.helix_deg)
            edge = math.cos(beta) * tangent + math.sin(beta) * around  # a right-hand helix
            direction = _fluted_direction(c_hat, n, edge, math.radians(cutter.rake_deg),
                                          math.radians(cutter.friction_deg))
        else:
            direction = -c_hat - params.k * n
        forces = ft[:, None] * direction
        samples = np.concatenate([
            forces, np.cross(x, forces), (ft * speed)[:, None], swept[:, None],
            np.full((_N_SAMPLES, 1), rho), (rho * speed)[:, None]], axis=1)  # (8, 10)
        # Exact Fourier coefficients of a degree-3 trigonometric polynomial from 8 samples.
        a0 = samples.mean(axis=0)
        cos_k = np.cos(np.outer(_DEGREES, _PHI_SAMPLES))
        sin_k = np.sin(np.outer(_DEGREES, _PHI_SAMPLES))
        ak = 2.0 / _N_SAMPLES * cos_k @ samples
        bk = 2.0 / _N_SAMPLES * sin_k @ samples
        total = np.zeros(_N_OUT)
        for lo, hi in intervals:
            total += a0 * (hi - lo)
            total += ((np.sin(_DEGREES * hi) - np.sin(_DEGREES * lo)) / _DEGREES) @ ak
            total -= ((np.cos(_DEGREES * hi) - np.cos(_DEGREES * lo)) / _DEGREES) @ bk
        return total

    from scipy.integrate import quad_vec  # here: see reference.py

    total = np.zeros(_N_OUT)
    for seg in burr.shape.profile():
        part, _err = quad_vec(lambda u, seg=seg: ring(seg, u), 0.0, 1.0, epsrel=epsrel,
                              epsabs=1e-14, limit=20000)
        total += seg.length_mm * part
    return result_from_totals(total)
