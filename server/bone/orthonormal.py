"""Snapping a nearly orthonormal 3×3 matrix onto the orthonormal ones, and only when it needs it.

A grid's direction goes through here each time it is built, so also on every save and reload:
a matrix that is already orthonormal to within float64 round-off is returned as it is, bit for
bit, which makes a geometry round trip exact. Only what is further off (a file that stores its
direction to a few decimals) is replaced by its orthogonal polar factor.

Nothing here calls BLAS or LAPACK (no ``@``, no ``np.linalg``): their kernels differ from one
processor or ``OPENBLAS_CORETYPE`` to another in the last bit, and a snapped direction must not.
Element-wise float64 arithmetic is correctly rounded everywhere, so the same input gives the
same bits on every machine.
"""

from __future__ import annotations

import numpy as np

#: Largest |MᵀM − I| entry (unitless) of a matrix kept as it is: 45 float64 ulps of 1. Rotations
#: computed in float64 (Euler angles, quaternions, an SVD's polar factor) are within ~15 ulps;
#: :func:`nearest_orthonormal`'s own results within ~5, so snapping twice changes nothing. A
#: direction kept with this error moves a point 1 m away by 10 fm.
ROUND_OFF = 1e-14

#: Newton steps allowed; from the 1e-3 shear a loader accepts, 4 reach round-off.
MAX_STEPS = 30


def gram_error(m: np.ndarray) -> float:
    """max |MᵀM − I| over the entries: how far the columns of the (3, 3) ``m`` are from
    orthonormal (unitless)."""
    gram = (m[:, :, None] * m[:, None, :]).sum(axis=0)
    return float(np.abs(gram - np.eye(3)).max())


def nearest_orthonormal(m: np.ndarray) -> np.ndarray:
    """``m`` itself when its columns are orthonormal within :data:`ROUND_OFF`, else the nearest
    orthonormal matrix (the orthogonal polar factor; the determinant keeps its sign).

    Args:
        m: a finite, non-singular (3, 3) float64 matrix.

    Raises:
        ValueError: ``m`` is singular or too far from orthonormal for the iteration to settle.
    """
    if gram_error(m) <= ROUND_OFF:
        return m
    # Newton's iteration for the polar factor, X ← (X + X⁻ᵀ)/2: quadratic near the answer.
    x = m
    for _ in range(MAX_STEPS):
        x = 0.5 * (x + _inverse_transpose(x))
        if gram_error(x) <= ROUND_OFF:
            return x
    raise ValueError(f"cannot orthonormalise {m.tolist()}: columns too far from orthonormal")


def _inverse_transpose(m: np.ndarray) -> np.ndarray:
    # M⁻ᵀ's columns are the cross products of M's other two columns over det M.
    a, b, c = m[:, 0], m[:, 1], m[:, 2]
    bc, ca, ab = _cross(b, c), _cross(c, a), _cross(a, b)
    det = a[0] * bc[0] + a[1] * bc[1] + a[2] * bc[2]
    if not np.isfinite(det) or det == 0.0:
        raise ValueError(f"cannot orthonormalise {m.tolist()}: it is singular")
    return np.stack([bc, ca, ab], axis=1) / det


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                     u[0] * v[1] - u[1] * v[0]])
