"""Burr shapes: a burr is a geometry (a solid of revolution) plus its cutter (abrasive or flutes).

Tool frame of a shape (model.md, "Burr shapes"): z along the tool axis toward the handle, ρ the
distance from the axis; the origin is the burr's reference centre (the sphere's centre, the
mid-length point on the axis of the others). A shape's profile is the generatrix of its closed
solid: segments from the tip (ρ = 0, lowest z) to the top (ρ = 0, highest z), straight lines and
exact circular arcs. The outward normal of a segment with tangent (dρ, dz) is (dz, −dρ)/|·|.

Every class here is a frozen, validated value with ``to_dict``/``from_dict`` (JSON-able), so the
same description can travel over REST.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass
from dataclasses import fields as dataclass_fields
from typing import Any, ClassVar, Literal

import numpy as np

from .vibration import flute_harmonic

#: Radii and lengths a model-level shape accepts, mm (the REST edge narrows this further).
MIN_SIZE_MM = 0.01
MAX_SIZE_MM = 100.0


def _check_size(name: str, value: object, *, zero_ok: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {type(value).__name__}")
    value = float(value)
    low = 0.0 if zero_ok else MIN_SIZE_MM
    if not math.isfinite(value) or not low <= value <= MAX_SIZE_MM:
        raise ValueError(f"{name} must be finite and in [{low}, {MAX_SIZE_MM}] mm, got {value}")
    return value


def _check_keys(cls_name: str, data: dict[str, Any], allowed: set[str]) -> None:
    if not isinstance(data, dict):
        raise ValueError(f"{cls_name} must be given as a mapping, got {type(data).__name__}")
    unknown = set(data) - allowed - {"kind"}
    if unknown:
        raise ValueError(f"unknown {cls_name} field(s) {sorted(unknown)}; "
                         f"expected {sorted(allowed)}")


# --- The profile: straight segments and exact arcs -------------------------------------------

@dataclass(frozen=True)
class Line:
    """A straight profile segment from (rho0, z0) to (rho1, z1), mm."""

    rho0: float
    z0: float
    rho1: float
    z1: float

    @property
    def length_mm(self) -> float:
        return math.hypot(self.rho1 - self.rho0, self.z1 - self.z0)

    def at(self, u: np.ndarray) -> tuple[np.ndarray, ...]:
        """(ρ, z, n_ρ, n_z, t_ρ, t_z, κ) at fractions ``u`` ∈ [0, 1] of the arc length: point
        (mm), outward unit normal, unit tangent (tip → top) and curvature (1/mm), shape of u."""
        u = np.asarray(u, dtype=np.float64)
        length = self.length_mm
        tr = (self.rho1 - self.rho0) / length
        tz = (self.z1 - self.z0) / length
        one = np.ones_like(u)
        return (self.rho0 + u * (self.rho1 - self.rho0), self.z0 + u * (self.z1 - self.z0),
                tz * one, -tr * one, tr * one, tz * one, 0.0 * one)


@dataclass(frozen=True)
class Arc:
    """A circular profile arc: centre (rho_c, z_c), radius r (mm), from angle psi0 to psi1 (rad;
    the point is (rho_c + r·cos ψ, z_c + r·sin ψ)). ψ increasing bulges outward (convex)."""

    rho_c: float
    z_c: float
    r: float
    psi0: float
    psi1: float

    @property
    def length_mm(self) -> float:
        return self.r * abs(self.psi1 - self.psi0)

    def at(self, u: np.ndarray) -> tuple[np.ndarray, ...]:
        """As :meth:`Line.at`; points, normals and tangents exact on the arc."""
        u = np.asarray(u, dtype=np.float64)
        psi = self.psi0 + u * (self.psi1 - self.psi0)
        c, s = np.cos(psi), np.sin(psi)
        sign = 1.0 if self.psi1 > self.psi0 else -1.0
        # Tangent (−sin ψ, cos ψ)·sign; normal (dz, −dρ) = sign·(cos ψ, sin ψ).
        return (self.rho_c + self.r * c, self.z_c + self.r * s, sign * c, sign * s,
                -sign * s, sign * c, np.full_like(u, 1.0 / self.r))


Segment = Line | Arc


def profile_points(profile: tuple[Segment, ...], per_arc: int = 16) -> np.ndarray:
    """The profile as a polyline of (ρ_k, z_k), mm, shape (n, 2), tip to top; each arc is
    sampled at ``per_arc`` chords (for drawing; the grid and the reference use the exact arcs)."""
    points = []
    for seg in profile:
        u = np.linspace(0.0, 1.0, per_arc + 1) if isinstance(seg, Arc) else np.array([0.0, 1.0])
        rho, z = seg.at(u)[:2]
        start = 0 if not points else 1
        points.extend(zip(rho[start:].tolist(), z[start:].tolist(), strict=True))
    return np.array(points, dtype=np.float64)


# --- Geometries ------------------------------------------------------------------------------

class BurrShape:
    """A burr's geometry: a closed solid of revolution about the tool axis."""

    kind: ClassVar[str]

    def profile(self) -> tuple[Segment, ...]:
        """The generatrix, tip (ρ = 0) to top (ρ = 0), in the tool frame (mm)."""
        raise NotImplementedError

    @property
    def max_radius_mm(self) -> float:
        """The largest ρ of the profile, mm."""
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        raise NotImplementedError

    @staticmethod
    def from_dict(data: dict[str, Any]) -> BurrShape:
        """The shape a :meth:`to_dict` mapping describes; ValueError says what is wrong."""
        if not isinstance(data, dict):
            raise ValueError(f"a burr shape must be a mapping, got {type(data).__name__}")
        kind = data.get("kind")
        classes = {c.kind: c for c in (Sphere, Cylinder, Barrel)}
        if not isinstance(kind, str) or kind not in classes:
            raise ValueError(f"burr shape kind must be one of {sorted(classes)}, got {kind!r}")
        return classes[kind]._from_fields(data)

    @classmethod
    def _from_fields(cls, data: dict[str, Any]) -> BurrShape:
        fields = {f.name: f for f in dataclass_fields(cls)}  # type: ignore[arg-type]
        _check_keys(f"{cls.kind} shape", data, set(fields))
        missing = {name for name, f in fields.items()
                   if f.default is MISSING and name not in data}
        if missing:
            raise ValueError(f"{cls.kind} shape is missing {sorted(missing)}")
        return cls(**{k: data[k] for k in fields if k in data})


@dataclass(frozen=True)
class Sphere(BurrShape):
    """A round burr of radius ``radius_mm`` (a "4 mm burr" has radius 2 mm); the reference
    centre is the sphere's centre."""

    kind: ClassVar[str] = "sphere"
    radius_mm: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "radius_mm", _check_size("radius_mm", self.radius_mm))

    def profile(self) -> tuple[Segment, ...]:
        return (Arc(0.0, 0.0, self.radius_mm, -0.5 * math.pi, 0.5 * math.pi),)

    @property
    def max_radius_mm(self) -> float:
        return self.radius_mm

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "radius_mm": self.radius_mm}


@dataclass(frozen=True)
class Cylinder(BurrShape):
    """A cylindrical burr: radius ``radius_mm``, overall length ``length_mm`` from tip to top,
    tip ``end`` "flat" (a disc) or "round" (a hemisphere of the same radius, inside the
    length). The top, toward the shank, is a flat disc. Reference centre at mid-length."""

    kind: ClassVar[str] = "cylinder"
    radius_mm: float
    length_mm: float
    end: Literal["flat", "round"] = "flat"

    def __post_init__(self) -> None:
        object.__setattr__(self, "radius_mm", _check_size("radius_mm", self.radius_mm))
        object.__setattr__(self, "length_mm", _check_size("length_mm", self.length_mm))
        if self.end not in ("flat", "round"):
            raise ValueError(f"cylinder end must be 'flat' or 'round', got {self.end!r}")
        if self.end == "round" and not self.length_mm > self.radius_mm:
            raise ValueError(
                f"a round-ended cylinder needs length_mm > radius_mm (the hemisphere is inside "
                f"the length), got length_mm={self.length_mm}, radius_mm={self.radius_mm}"
            )

    def profile(self) -> tuple[Segment, ...]:
        r, h = self.radius_mm, 0.5 * self.length_mm
        top = Line(r, h, 0.0, h)
        if self.end == "flat":
            return (Line(0.0, -h, r, -h), Line(r, -h, r, h), top)
        return (Arc(0.0, -h + r, r, -0.5 * math.pi, 0.0), Line(r, -h + r, r, h), top)

    @property
    def max_radius_mm(self) -> float:
        return self.radius_mm

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "radius_mm": self.radius_mm, "length_mm": self.length_mm,
                "end": self.end}


@dataclass(frozen=True)
class Barrel(BurrShape):
    """A barrel burr: a circular-arc profile through the end rims (ρ = ``end_radius_mm`` at
    z = ±length/2) and the equator (ρ = ``equator_radius_mm`` at z = 0), closed by flat end
    discs (none when the end radius is 0: a lens). The arc must bulge no further than a
    half-circle: equator − end radius ≤ length/2. Reference centre at mid-length."""

    kind: ClassVar[str] = "barrel"
    equator_radius_mm: float
    end_radius_mm: float
    length_mm: float

    def __post_init__(self) -> None:
        eq = _check_size("equator_radius_mm", self.equator_radius_mm)
        end = _check_size("end_radius_mm", self.end_radius_mm, zero_ok=True)
        length = _check_size("length_mm", self.length_mm)
        object.__setattr__(self, "equator_radius_mm", eq)
        object.__setattr__(self, "end_radius_mm", end)
        object.__setattr__(self, "length_mm", length)
        if not end < eq:
            raise ValueError(f"a barrel needs end_radius_mm < equator_radius_mm, got "
                             f"end_radius_mm={end}, equator_radius_mm={eq}")
        if eq - end > 0.5 * length:
            raise ValueError(
                f"a barrel's bulge equator_radius_mm − end_radius_mm = {eq - end} mm must not "
                f"exceed length_mm/2 = {0.5 * length} mm (its arc would pass a half-circle)"
            )

    @property
    def arc_radius_mm(self) -> float:
        """Radius of the profile's circular arc, mm."""
        d = self.equator_radius_mm - self.end_radius_mm
        return (d * d + 0.25 * self.length_mm ** 2) / (2.0 * d)

    def profile(self) -> tuple[Segment, ...]:
        r = self.arc_radius_mm
        h = 0.5 * self.length_mm
        psi = math.asin(min(1.0, h / r))
        arc = Arc(self.equator_radius_mm - r, 0.0, r, -psi, psi)
        if self.end_radius_mm == 0.0:
            return (arc,)
        e = self.end_radius_mm
        return (Line(0.0, -h, e, -h), arc, Line(e, h, 0.0, h))

    @property
    def max_radius_mm(self) -> float:
        return self.equator_radius_mm

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "equator_radius_mm": self.equator_radius_mm,
                "end_radius_mm": self.end_radius_mm, "length_mm": self.length_mm}


# --- Cutters ---------------------------------------------------------------------------------

class Cutter:
    """What removes the bone on the burr's surface: abrasive grit or cutting flutes."""

    kind: ClassVar[str]

    def force_ratios(self, k: float) -> tuple[float, float]:
        """(normal, edge) force per unit tangential force on a surface element (model.md,
        "Burr shapes"): the normal part pushes the burr out of the bone along −n, the edge part
        acts along the profile tangent (tip → top) for Ω along +a (the kernel flips it with the
        spin). ``k`` is the abrasive K."""
        raise NotImplementedError

    @property
    def harmonic(self) -> float:
        """Vibration frequency in multiples of the rotation rate."""
        raise NotImplementedError

    @property
    def calibrated(self) -> bool:
        """Whether measured forces back this cutter's model."""
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        raise NotImplementedError

    @staticmethod
    def from_dict(data: dict[str, Any]) -> Cutter:
        if not isinstance(data, dict):
            raise ValueError(f"a cutter must be a mapping, got {type(data).__name__}")
        kind = data.get("kind")
        if kind == "abrasive":
            _check_keys("abrasive cutter", data, set())
            return Abrasive()
        if kind == "fluted":
            fields = {f.name for f in dataclass_fields(Fluted)}
            _check_keys("fluted cutter", data, fields)
            if "n_flutes" not in data:
                raise ValueError("fluted cutter is missing ['n_flutes']")
            return Fluted(**{k: data[k] for k in fields if k in data})
        raise ValueError(f"cutter kind must be 'abrasive' or 'fluted', got {kind!r}")


@dataclass(frozen=True)
class Abrasive(Cutter):
    """Grit spread evenly over the surface (the thesis's diamond burr): normal = K·tangential."""

    kind: ClassVar[str] = "abrasive"

    def force_ratios(self, k: float) -> tuple[float, float]:
        return float(k), 0.0

    @property
    def harmonic(self) -> float:
        return 1.0

    @property
    def calibrated(self) -> bool:
        return True

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind}


@dataclass(frozen=True)
class Fluted(Cutter):
    """Discrete cutting edges (a tungsten-carbide cutting burr). NOT CALIBRATED: no measured
    forces back these defaults; they are illustrative.

    Attributes:
        n_flutes: number of edges, ≥ 1; sets the vibration harmonic (tooth-passing frequency).
        helix_deg: angle between an edge and the profile's generatrix, degrees, in (−60, 60);
            positive = right-hand helix (on a cylinder's side, the edge turns counter-clockwise
            seen from the handle as it rises toward the handle). It is the oblique-cutting
            inclination angle of the edge.
        rake_deg: normal rake angle of the edge, degrees, in [−45, 45].
        friction_deg: friction angle between chip and rake face, degrees, in [0, 60].
    """

    kind: ClassVar[str] = "fluted"
    n_flutes: int
    helix_deg: float = 0.0
    rake_deg: float = 0.0
    friction_deg: float = 30.0

    def __post_init__(self) -> None:
        if isinstance(self.n_flutes, bool) or not isinstance(self.n_flutes, (int, np.integer)):
            raise ValueError(f"n_flutes must be an integer, got {self.n_flutes!r}")
        flute_harmonic(int(self.n_flutes))  # raises with the range
        object.__setattr__(self, "n_flutes", int(self.n_flutes))
        for name, low, high, open_ in (("helix_deg", -60.0, 60.0, True),
                                       ("rake_deg", -45.0, 45.0, False),
                                       ("friction_deg", 0.0, 60.0, False)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{name} must be a number, got {value!r}")
            inside = low < value < high if open_ else low <= value <= high
            if not (math.isfinite(value) and inside):
                br = "()" if open_ else "[]"
                raise ValueError(f"{name} must be in {br[0]}{low}, {high}{br[1]} degrees, "
                                 f"got {value}")
            object.__setattr__(self, name, float(value))

    def force_ratios(self, k: float) -> tuple[float, float]:
        """Oblique cutting with Stabler's chip-flow rule η = i (Armarego & Whitfield 1985;
        Altintas, Manufacturing Automation, ch. 2): with normal rake αn, inclination i and
        rake-face friction angle βa, tan βn = tan βa·cos η and, per unit tangential force,
        normal = sin(βn−αn) / (cos i·(cos(βn−αn) + tan²i·sin βn)),
        edge = tan i·(cos(βn−αn) − sin βn) / (cos(βn−αn) + tan²i·sin βn).
        With i = 0 the normal ratio is Merchant's tan(βa − αn). ``k`` is not used."""
        del k
        i = math.radians(self.helix_deg)
        alpha_n = math.radians(self.rake_deg)
        beta_n = math.atan(math.tan(math.radians(self.friction_deg)) * math.cos(i))
        t2 = math.tan(i) ** 2
        denominator = math.cos(beta_n - alpha_n) + t2 * math.sin(beta_n)
        normal = math.sin(beta_n - alpha_n) / (math.cos(i) * denominator)
        edge = math.tan(i) * (math.cos(beta_n - alpha_n) - math.sin(beta_n)) / denominator
        return normal, edge

    @property
    def harmonic(self) -> float:
        return flute_harmonic(self.n_flutes)

    @property
    def calibrated(self) -> bool:
        return False

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "n_flutes": self.n_flutes, "helix_deg": self.helix_deg,
                "rake_deg": self.rake_deg, "friction_deg": self.friction_deg}


@dataclass(frozen=True)
class Burr:
    """A burr: its geometry and its cutter (abrasive by default)."""

    shape: BurrShape
    cutter: Cutter = Abrasive()

    def __post_init__(self) -> None:
        if not isinstance(self.shape, BurrShape):
            raise ValueError(f"shape must be a BurrShape, got {type(self.shape).__name__}")
        if not isinstance(self.cutter, Cutter):
            raise ValueError(f"cutter must be a Cutter, got {type(self.cutter).__name__}")

    def to_dict(self) -> dict[str, Any]:
        return {"shape": self.shape.to_dict(), "cutter": self.cutter.to_dict()}

    @staticmethod
    def from_dict(data: dict[str, Any]) -> Burr:
        if not isinstance(data, dict):
            raise ValueError(f"a burr must be a mapping, got {type(data).__name__}")
        _check_keys("burr", data, {"shape", "cutter"})
        if "shape" not in data:
            raise ValueError("burr is missing ['shape']")
        cutter = Cutter.from_dict(data["cutter"]) if "cutter" in data else Abrasive()
        return Burr(BurrShape.from_dict(data["shape"]), cutter)
