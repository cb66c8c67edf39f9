"""Engine frames and units, converted at the edge (SPEC.md, "Frames and units").

The server's frame is right-handed, millimetres, z up, x forward, y left (ROS's axes in mm).
Each engine frame is that frame's axes as the engine names them, plus a length unit; the
conversion is a signed permutation (det −1 for the left-handed engines) and a scale. Forces are
newtons in every frame; anything with a length in it uses the engine's length unit.

Torque is a pseudovector: an engine computes r × F with the same formula in its own axes, so
under a reflection its torque picks up det(M) — handled by :meth:`Transform.torque_out`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class Frame(NamedTuple):
    """An engine's frame.

    Attributes:
        name: the name sessions use.
        description: its axes in words.
        to_server: (3, 3) matrix M, rows of tuples: server vector = M · engine vector.
        mm_per_unit: millimetres per engine length unit.
        length_unit: that unit's symbol.
        tool_axis: the default local tool axis (from the burr toward the handle), engine axes.
    """

    name: str
    description: str
    to_server: tuple[Vec3, Vec3, Vec3]
    mm_per_unit: float
    length_unit: str
    tool_axis: Vec3

    @property
    def right_handed(self) -> bool:
        return float(np.linalg.det(np.array(self.to_server))) > 0.0


FRAMES: dict[str, Frame] = {f.name: f for f in (
    Frame("si_mm", "right-handed, millimetres; the server's own frame (z up, x forward)",
          ((1, 0, 0), (0, 1, 0), (0, 0, 1)), 1.0, "mm", (0.0, 0.0, 1.0)),
    Frame("unity", "Unity: left-handed, metres, y up, z forward, x right",
          ((0, 0, 1), (-1, 0, 0), (0, 1, 0)), 1000.0, "m", (0.0, 1.0, 0.0)),
    Frame("unreal", "Unreal Engine: left-handed, centimetres, z up, x forward, y right",
          ((1, 0, 0), (0, -1, 0), (0, 0, 1)), 10.0, "cm", (0.0, 0.0, 1.0)),
    Frame("godot", "Godot: right-handed, metres, y up, −z forward, x right",
          ((0, 0, -1), (-1, 0, 0), (0, 1, 0)), 1000.0, "m", (0.0, 1.0, 0.0)),
    Frame("ros", "ROS (REP 103): right-handed, metres, z up, x forward, y left",
          ((1, 0, 0), (0, 1, 0), (0, 0, 1)), 1000.0, "m", (0.0, 0.0, 1.0)),
)}
DEFAULT_FRAME = "si_mm"


def frame(name: str) -> Frame:
    """The frame called ``name``.

    Raises:
        ValueError: unknown name (the message lists the known ones).
    """
    try:
        return FRAMES[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown frame {name!r}; choose one of {', '.join(FRAMES)}") from None


def quat_rotate(q: Quat, v: Vec3) -> Vec3:
    """Rotate ``v`` by the quaternion ``q`` = (x, y, z, w), normalized here."""
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    vx, vy, vz = v
    # v' = v + 2w (q × v) + 2 q × (q × v)
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (vx + w * tx + (y * tz - z * ty),
            vy + w * ty + (z * tx - x * tz),
            vz + w * tz + (x * ty - y * tx))


def quat_matrix(q: Quat) -> np.ndarray:
    """(3, 3) rotation matrix of the quaternion (x, y, z, w)."""
    return np.array([quat_rotate(q, e) for e in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                                                  (0.0, 0.0, 1.0))]).T


class Transform:
    """Engine frame ↔ a target frame (right-handed, mm): the bone's grid, for a session.

    target = scale · A · engine + offset, with A = R_targetᵀ · R_placementᵀ · M orthogonal
    (det ±1). Built once per session; applied with plain float arithmetic (a few hundred ns,
    less than converting to numpy and back).

    Args:
        frame: the engine frame.
        placement_position: where the server frame's origin lies in the engine's world,
            engine units.
        placement_orientation: the server frame's rotation in the engine's world, an engine
            quaternion (x, y, z, w).
        target_rotation, target_origin_mm: the target frame in the server frame (the grid's
            ``direction`` and ``origin_mm``); default the server frame itself.
    """

    def __init__(self, frame: Frame, placement_position: Vec3 = (0.0, 0.0, 0.0),
                 placement_orientation: Quat = (0.0, 0.0, 0.0, 1.0),
                 target_rotation: np.ndarray | None = None,
                 target_origin_mm: np.ndarray | None = None) -> None:
        m = np.array(frame.to_server, dtype=np.float64)
        s = float(frame.mm_per_unit)
        r_place = m @ quat_matrix(placement_orientation) @ m.T
        t_place = s * (m @ np.asarray(placement_position, dtype=np.float64))
        g = np.eye(3) if target_rotation is None else np.asarray(target_rotation, np.float64)
        o = np.zeros(3) if target_origin_mm is None else np.asarray(target_origin_mm,
                                                                     np.float64)
        a = g.T @ r_place.T @ m
        self.frame = frame
        self.scale = s
        self.matrix = a
        self.offset_mm = -(g.T @ (r_place.T @ t_place + o))
        self.det = float(np.sign(np.linalg.det(a)))
        self._a = tuple(tuple(float(x) for x in row) for row in a)
        self._b = tuple(float(x) for x in self.offset_mm)

    # engine → target
    def point_in(self, p: Vec3) -> Vec3:
        (a0, a1, a2), (a3, a4, a5), (a6, a7, a8) = self._a
        s = self.scale
        x, y, z = p[0] * s, p[1] * s, p[2] * s
        b = self._b
        return (a0 * x + a1 * y + a2 * z + b[0], a3 * x + a4 * y + a5 * z + b[1],
                a6 * x + a7 * y + a8 * z + b[2])

    def vector_in(self, v: Vec3) -> Vec3:
        """A velocity or displacement: engine units → mm on the target's axes."""
        x, y, z = self.direction_in(v)
        s = self.scale
        return (x * s, y * s, z * s)

    def direction_in(self, d: Vec3) -> Vec3:
        """A direction (unitless): engine axes → target axes."""
        (a0, a1, a2), (a3, a4, a5), (a6, a7, a8) = self._a
        x, y, z = d
        return (a0 * x + a1 * y + a2 * z, a3 * x + a4 * y + a5 * z, a6 * x + a7 * y + a8 * z)

    # target → engine
    def direction_out(self, d: Vec3) -> Vec3:
        """A force (N) or direction: target axes → engine axes (Aᵀ, A is orthogonal)."""
        (a0, a1, a2), (a3, a4, a5), (a6, a7, a8) = self._a
        x, y, z = d
        return (a0 * x + a3 * y + a6 * z, a1 * x + a4 * y + a7 * z, a2 * x + a5 * y + a8 * z)

    def vector_out(self, v: Vec3) -> Vec3:
        """A velocity or displacement: mm → engine units."""
        x, y, z = self.direction_out(v)
        s = self.scale
        return (x / s, y / s, z / s)

    def point_out(self, p: Vec3) -> Vec3:
        b = self._b
        return self.vector_out((p[0] - b[0], p[1] - b[1], p[2] - b[2]))

    def torque_out(self, t: Vec3) -> Vec3:
        """A torque (pseudovector), N·mm on the target's axes → N·(engine unit)."""
        x, y, z = self.direction_out(t)
        k = self.det / self.scale
        return (x * k, y * k, z * k)
