"""Materials files: which label, segment or colour of a file is which material.

A materials file (TOML or JSON) says what a loaded volume is made of::

    unlisted = "own"        # label values no rule names: "own" (each its own material, cut
                            # like the thesis's cortical bone), "error", or a material's name

    [materials.cortical]    # built-in names (cortical, trabecular, nerve) need no Us or K
    labels = [1]            # label-map values
    segments = ["Bone"]     # 3D Slicer segment names (case-insensitive)
    colors = ["#ffffff"]    # colours of an RGB(A) PNG stack

    [materials.facial_nerve]
    us_n_mm2 = 0.0
    k = 0.0
    forbidden = true
    labels = [3]

    [ct]                    # CT volumes: HU bands → materials (default: the bone presets)
    above_top = true
    partial_volume_hu = 0
    bands = [{material = "trabecular", min_hu = 148, max_hu = 661},
             {material = "cortical", min_hu = 662, max_hu = 1988}]
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from .hounsfield import CTMapping, HUBand
from .materials import (
    BUILTIN_MATERIALS,
    CORTICAL,
    MAX_NAME_LENGTH,
    N_LABELS,
    TRABECULAR,
    Material,
    MaterialTable,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: Materials files are small; anything larger is not one.
MAX_MAP_BYTES = 1 << 20
_MATERIAL_KEYS = {"us_n_mm2", "k", "forbidden", "labels", "segments", "colors"}


@dataclass(frozen=True)
class Segment:
    """What a file says about one label value: a segment name and/or an RGB colour."""

    name: str | None = None
    color: tuple[int, int, int] | None = None

    def display_name(self, value: int) -> str:
        if self.name:
            return self.name
        if self.color is not None:
            return color_hex(self.color)
        return f"label {value}"


@dataclass(frozen=True)
class MaterialRule:
    material: Material
    labels: frozenset[int] = frozenset()
    segments: frozenset[str] = frozenset()  # lower-cased
    colors: frozenset[str] = frozenset()  # "#rrggbb"


@dataclass(frozen=True)
class MaterialMap:
    """Rules from label values to materials, and the CT bands.

    Attributes:
        rules: one per material, in the file's order.
        unlisted: "own", "error" or a material name (see the module docstring).
        ct: the HU bands for CT volumes.
        source: the file it came from ("" for the defaults).
    """

    rules: tuple[MaterialRule, ...] = (MaterialRule(CORTICAL), MaterialRule(TRABECULAR))
    unlisted: str = "own"
    ct: CTMapping = field(default_factory=CTMapping)
    source: str = ""

    def material(self, name: str) -> Material:
        for rule in self.rules:
            if rule.material.name == name:
                return rule.material
        raise KeyError(name)

    @classmethod
    def from_file(cls, path: str | Path) -> MaterialMap:
        """Read a TOML (``.toml``) or JSON file. ValueError names the file and the problem."""
        path = Path(path)
        try:
            size = path.stat().st_size
            if size > MAX_MAP_BYTES:
                raise ValueError(f"{size} bytes is too large for a materials file")
            text = path.read_text(encoding="utf-8")
            data = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
            return cls.from_dict(data, source=str(path))
        except OSError as exc:
            raise ValueError(f"{path}: cannot read the materials file: {exc.strerror}") from None
        except (ValueError, TypeError, KeyError) as exc:  # TOMLDecodeError is a ValueError
            raise ValueError(f"{path}: {exc}") from None

    @classmethod
    def from_dict(cls, data: object, source: str = "") -> MaterialMap:
        if not isinstance(data, Mapping):
            raise ValueError("a materials file holds a table (materials, unlisted, ct)")
        unknown = set(data) - {"materials", "unlisted", "ct"}
        if unknown:
            raise ValueError(f"unknown keys {sorted(unknown)} (known: materials, unlisted, ct)")
        tables = data.get("materials", {})
        if not isinstance(tables, Mapping):
            raise ValueError("'materials' must be a table of material tables")
        rules = [_rule(name, table) for name, table in tables.items()]
        if len(rules) > N_LABELS - 1:
            raise ValueError(f"{len(rules)} materials; at most {N_LABELS - 1} fit")
        by_name = {r.material.name: r.material for r in rules}
        ct = _ct_mapping(data.get("ct", {}), by_name)
        # Band materials not listed under [materials] are built-ins; add them.
        for band in ct.bands:
            if band.material not in by_name:
                rules.append(MaterialRule(BUILTIN_MATERIALS[band.material]))
                by_name[band.material] = BUILTIN_MATERIALS[band.material]
        unlisted = data.get("unlisted", "own")
        if isinstance(unlisted, str) and unlisted not in by_name \
                and unlisted in BUILTIN_MATERIALS:
            rules.append(MaterialRule(BUILTIN_MATERIALS[unlisted]))
            by_name[unlisted] = BUILTIN_MATERIALS[unlisted]
        if not isinstance(unlisted, str) or (unlisted not in ("own", "error")
                                             and unlisted not in by_name):
            raise ValueError(f"unlisted must be 'own', 'error' or a material's name, "
                             f"got {unlisted!r}")
        _check_unique_selectors(rules)
        return cls(tuple(rules), unlisted, ct, source)

    def assign(
        self, values: list[int], segments: Mapping[int, Segment] | None = None,
        match_values: bool = True,
    ) -> tuple[dict[int, int], MaterialTable]:
        """Material labels for the label values present in a volume.

        Args:
            values: the distinct non-zero label values in the volume.
            segments: what the file says about each value (names, colours).
            match_values: whether the values are the file's own label values (a label map),
                which ``labels`` rules may name; False when a reader numbered segments or
                colours itself.

        Returns:
            ``(label_of_value, table)``: each value's material label (1..255) and a table of
            the materials used, numbered in the file's order, then the unlisted ones.

        Raises:
            ValueError: values no rule names when ``unlisted = "error"``; too many materials.
        """
        segments = segments or {}
        chosen: dict[int, Material] = {}
        orphans: list[int] = []
        for value in values:
            rule = self._rule_for(value if match_values else None, segments.get(value))
            if rule is not None:
                chosen[value] = rule.material
            elif self.unlisted == "own":
                orphans.append(value)
            elif self.unlisted == "error":
                seg = segments.get(value)
                what = f" ({seg.display_name(value)})" if seg else ""
                raise ValueError(f"label value {value}{what} is not in the materials file "
                                 f"{self.source or '(defaults)'} and unlisted = 'error'")
            else:
                chosen[value] = self.material(self.unlisted)
        used = [r.material for r in self.rules if r.material in chosen.values()]
        taken = {m.name for m in used}
        for value in orphans:
            seg = segments.get(value) or Segment()
            # A segment named after a built-in material ("Nerve", "trabecular") is that
            # material, with its Us, K and forbidden flag, never a look-alike cut as cortical.
            builtin = BUILTIN_MATERIALS.get(seg.display_name(value).strip().lower())
            if builtin is not None and builtin.name not in taken:
                material = builtin
            elif builtin is not None:
                material = next(m for m in used if m.name == builtin.name)
            else:
                name = _unique(_printable(seg.display_name(value)), taken)
                material = Material(name, CORTICAL.us_n_mm2, CORTICAL.k)
            if material.name not in taken:
                taken.add(material.name)
                used.append(material)
            chosen[value] = material
        if len(used) > N_LABELS - 1:
            raise ValueError(f"the volume has {len(used)} materials; at most {N_LABELS - 1} "
                             "fit: map several label values onto one material")
        table = MaterialTable({i + 1: m for i, m in enumerate(used)})
        label_of_material = {m.name: i + 1 for i, m in enumerate(used)}
        return {v: label_of_material[m.name] for v, m in chosen.items()}, table

    def is_forbidden(self, value: int, segment: Segment | None) -> bool:
        """Whether label ``value`` (with what the file says about it) maps to a forbidden
        material — so a reader can let critical structures win where segments overlap."""
        rule = self._rule_for(None, segment)
        if rule is None and self.unlisted not in ("own", "error"):
            return self.material(self.unlisted).forbidden
        return rule is not None and rule.material.forbidden

    def ct_table(self) -> tuple[list[int], MaterialTable]:
        """The table for a CT volume (the bands' materials, in the file's order) and each
        band's label."""
        names = []
        for rule in self.rules:
            if any(b.material == rule.material.name for b in self.ct.bands):
                names.append(rule.material.name)
        table = MaterialTable({i + 1: self.material(n) for i, n in enumerate(names)})
        return [names.index(b.material) + 1 for b in self.ct.bands], table

    def _rule_for(self, value: int | None, segment: Segment | None) -> MaterialRule | None:
        for rule in self.rules:
            if value is not None and value in rule.labels:
                return rule
            if segment is not None:
                if segment.name and segment.name.strip().lower() in rule.segments:
                    return rule
                if segment.color is not None and color_hex(segment.color) in rule.colors:
                    return rule
        return None


def color_hex(rgb: tuple[int, int, int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def _rule(name: object, table: object) -> MaterialRule:
    if not isinstance(table, Mapping):
        raise ValueError(f"material {name!r} must be a table")
    unknown = set(table) - _MATERIAL_KEYS
    if unknown:
        raise ValueError(f"material {name!r}: unknown keys {sorted(unknown)} "
                         f"(known: {', '.join(sorted(_MATERIAL_KEYS))})")
    base = BUILTIN_MATERIALS.get(str(name))
    if base is None and not {"us_n_mm2", "k"} <= set(table):
        raise ValueError(f"material {name!r} is not built in "
                         f"({', '.join(BUILTIN_MATERIALS)}): give us_n_mm2 and k")
    fields = {f: table[f] for f in ("us_n_mm2", "k", "forbidden") if f in table}
    if base is None:
        material = Material(str(name), **fields)
    else:
        material = Material(base.name, **{"us_n_mm2": base.us_n_mm2, "k": base.k,
                                          "forbidden": base.forbidden, **fields})
    labels = _list(name, table, "labels", int)
    if any(isinstance(v, bool) for v in labels):
        raise ValueError(f"material {name!r}: labels must be integers")
    if 0 in labels:
        raise ValueError(f"material {name!r}: label value 0 is empty space")
    segments = frozenset(s.strip().lower() for s in _list(name, table, "segments", str))
    colors = frozenset(_parse_color(name, c) for c in _list(name, table, "colors", str))
    return MaterialRule(material, frozenset(labels), segments, colors)


def _list(name: object, table: Mapping, key: str, kind: type) -> list:
    values = table.get(key, [])
    if not isinstance(values, list) or not all(isinstance(v, kind) for v in values):
        raise ValueError(f"material {name!r}: {key} must be a list of {kind.__name__}s")
    return values


def _parse_color(name: object, text: str) -> str:
    hex_part = text.strip().lstrip("#").lower()
    if len(hex_part) != 6 or any(c not in "0123456789abcdef" for c in hex_part):
        raise ValueError(f"material {name!r}: colour {text!r} is not #rrggbb")
    return "#" + hex_part


def _check_unique_selectors(rules: list[MaterialRule]) -> None:
    for kind in ("labels", "segments", "colors"):
        seen: dict[object, str] = {}
        for rule in rules:
            for value in getattr(rule, kind):
                if value in seen:
                    raise ValueError(f"{kind[:-1]} {value!r} is given to both "
                                     f"{seen[value]!r} and {rule.material.name!r}")
                seen[value] = rule.material.name


def _ct_mapping(table: object, by_name: Mapping[str, Material]) -> CTMapping:
    if not isinstance(table, Mapping):
        raise ValueError("'ct' must be a table")
    unknown = set(table) - {"bands", "above_top", "partial_volume_hu"}
    if unknown:
        raise ValueError(f"ct: unknown keys {sorted(unknown)} "
                         "(known: bands, above_top, partial_volume_hu)")
    kwargs = {}
    if "bands" in table:
        bands = table["bands"]
        if not isinstance(bands, list) or not all(isinstance(b, Mapping) for b in bands):
            raise ValueError("ct.bands must be a list of {material, min_hu, max_hu} tables")
        parsed = []
        for band in bands:
            if set(band) != {"material", "min_hu", "max_hu"}:
                raise ValueError(f"ct band {dict(band)!r} needs exactly material, min_hu, max_hu")
            name = band["material"]
            if name not in by_name and name not in BUILTIN_MATERIALS:
                raise ValueError(f"ct band material {name!r} is neither listed under "
                                 "[materials] nor built in")
            parsed.append(HUBand(name, band["min_hu"], band["max_hu"]))
        kwargs["bands"] = tuple(parsed)
    if "above_top" in table:
        if not isinstance(table["above_top"], bool):
            raise ValueError("ct.above_top must be true or false")
        kwargs["above_top"] = table["above_top"]
    if "partial_volume_hu" in table:
        kwargs["partial_volume_hu"] = table["partial_volume_hu"]
    mapping = CTMapping(**kwargs)
    for band in mapping.bands:
        if band.material not in by_name and band.material not in BUILTIN_MATERIALS:
            raise ValueError(f"ct band material {band.material!r} is not defined")
    return mapping


def _printable(name: str) -> str:
    cleaned = "".join(c if c.isprintable() else " " for c in name).strip()
    return (cleaned or "segment")[:MAX_NAME_LENGTH]


def _unique(name: str, taken: set[str]) -> str:
    if name not in taken:
        return name
    for i in range(2, N_LABELS + 1):
        suffix = f" ({i})"
        candidate = name[:MAX_NAME_LENGTH - len(suffix)] + suffix
        if candidate not in taken:
            return candidate
    raise ValueError(f"too many materials named {name!r}")
