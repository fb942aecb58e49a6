"""Street kinds: the settings that make a synthetic street like the data a city brings.

A :class:`StreetKind` says how a street is seen and how its cloud is written:

* ``path``: where the cameras go. ``vehicle`` (the default) walks the near sidewalk looking
  straight across at the far side; ``sidewalk-right`` is a pedestrian on the near sidewalk
  (−y in the street frame, on the right when walking +x) looking forward and obliquely across
  the street, so the far side's objects are seen at 35–55° from 10–20 m; ``sidewalk-left`` is
  a pedestrian on the far sidewalk (+y) behind the street furniture, looking along the street
  and a little towards the road, so the objects of its own sidewalk are seen from 8–20 m ahead.
* ``plain``: the street inventory (poles, signs, boards, bins, benches, railings) painted in
  one uniform colour per object with no texture, and plain walls along the property line,
  about 1 m behind the boards and benches of the middle of the far sidewalk.
* ``colour``: False writes the cloud without RGB (LAS point format 6 instead of 7).
* ``density``: keep this fraction of the scanned points (at random, 0 < density ≤ 1).
* ``point_spacing_m``: scan with this point spacing at 10 m range instead of ~0.05 m (a
  coarser scanner: automotive or airborne-like density); the two can be combined.
* ``class_codes``: the coding of the roles in the written cloud (:data:`SCHEMES`, or a YAML
  file holding ``detect: classes:``); a coded street gets ``streetcd.yaml`` next to it with
  the class map that ``--config`` must be given. ``None`` is the default: streetcd's codes
  (:mod:`streetcd.classes`) and no config file; ``unclassified`` writes every point as 1.

:data:`PRESETS` names combinations (``streetcd synth --kind NAME``); explicit settings
override a preset's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from streetcd import classes as C
from streetcd.errors import InputError

PATHS = ("vehicle", "sidewalk-left", "sidewalk-right")

# The roles of the detector's class map, in the order the config file lists them.
ROLES = (
    "ground",
    "road",
    "vegetation",
    "building",
    "pole",
    "sign",
    "railing",
    "furniture",
    "vehicle",
)

# streetcd's own code for each role (what the scene's primitives carry)
_ROLE_OF_CLASS = {
    C.GROUND: "ground",
    C.ROAD: "road",
    C.VEGETATION: "vegetation",
    C.BUILDING: "building",
    C.POLE: "pole",
    C.SIGN: "sign",
    C.RAILING: "railing",
    C.FURNITURE: "furniture",
    C.CAR: "vehicle",
}


@dataclass(frozen=True)
class ClassScheme:
    """A coding of the roles: ``roles`` role → codes (0–255; the first is the one written
    unless ``by_type`` says otherwise), ``by_type`` object type → code for the points of that
    type's own class (a hedge among the trees' vegetation, a board among the signs)."""

    name: str
    roles: dict[str, tuple[int, ...]]
    by_type: dict[str, int]

    def lookup(self) -> np.ndarray:
        """(256,) uint8: streetcd code → written code (unknown codes → 1, unclassified)."""
        table = np.full(256, C.UNCLASSIFIED, np.uint8)
        for code, role in _ROLE_OF_CLASS.items():
            table[code] = self.roles[role][0]
        return table

    def codes(
        self, cls: np.ndarray, obj: np.ndarray, objects: dict[int, dict[str, Any]]
    ) -> np.ndarray:
        """Written codes (N,) uint8 for points of streetcd codes ``cls`` (N,) on objects
        ``obj`` (N,) (ids into ``objects``: id → {type, class})."""
        out = self.lookup()[cls]
        if not self.by_type or not len(obj):
            return out
        size = max(objects) + 1
        own = np.zeros(size, np.int16)  # each object's own class
        special = np.full(size, -1, np.int16)  # its type's code, −1 where none
        for oid, ob in objects.items():
            own[oid] = ob["class"]
            special[oid] = self.by_type.get(ob["type"], -1)
        code = special[obj]
        sel = (code >= 0) & (cls == own[obj])  # a sign's post keeps the pole code
        out[sel] = code[sel]
        return out

    def names(self) -> dict[str, str]:
        """Written code → role name, for the manifest."""
        out: dict[str, str] = {}
        for role, codes in self.roles.items():
            for code in codes:
                out.setdefault(str(code), role)
        return out

    def config_text(self) -> str:
        """The ``streetcd.yaml`` that makes the detector read this coding."""
        lines = [
            f"# class map of a synthetic street coded '{self.name}' (streetcd synth)",
            "detect:",
            "  classes:            # the cloud's codes for each role the method needs",
        ]
        for role in ROLES:
            codes = ", ".join(str(c) for c in self.roles[role])
            lines.append(f"    {role}: [{codes}]")
        return "\n".join(lines) + "\n"


SCHEMES: dict[str, ClassScheme] = {
    # streetcd's own codes (streetcd.classes): ASPRS where the standard names the class,
    # user codes 64–68 for the street objects
    "streetcd": ClassScheme(
        "streetcd",
        {
            "ground": (C.GROUND,),
            "road": (C.ROAD,),
            "vegetation": (C.VEGETATION,),
            "building": (C.BUILDING,),
            "pole": (C.POLE,),
            "sign": (C.SIGN,),
            "railing": (C.RAILING,),
            "furniture": (C.FURNITURE,),
            "vehicle": (C.CAR,),
        },
        {},
    ),
    # ASPRS LAS 1.4 codes only, all below 32 so that LAS 1.2's formats could hold them:
    # the standard's own class where it has one (hedges 4 medium, trees 5 high vegetation),
    # and for the street objects it does not name, standard codes a city reuses for them
    # (15 tower for poles, 19 overhead structure for signs, 13 guard wire for railings,
    # 16 wire-structure connector for furniture, 17 bridge deck for vehicles)
    "asprs": ClassScheme(
        "asprs",
        {
            "ground": (2,),
            "road": (11,),
            "vegetation": (5, 4, 3),
            "building": (6,),
            "pole": (15,),
            "sign": (19,),
            "railing": (13,),
            "furniture": (16,),
            "vehicle": (17,),
        },
        {"hedge": 4},
    ),
    # a city's own scheme: codes above 100, several codes for some roles
    "city": ClassScheme(
        "city",
        {
            "ground": (202, 203),
            "road": (201,),
            "vegetation": (230, 231),
            "building": (210,),
            "pole": (101,),
            "sign": (102, 107),
            "railing": (103,),
            "furniture": (104, 108),
            "vehicle": (120,),
        },
        {"hedge": 231, "board": 107, "bin": 108},
    ),
}
UNCLASSIFIED = "unclassified"


def _is_code(c: object) -> bool:
    return isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= 255


def load_scheme(path: str | Path) -> ClassScheme:
    """A custom coding from a YAML file with ``detect: classes:`` (or ``classes:``) giving
    every role a list of codes 0–255."""
    import yaml

    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"{p}: cannot read the class codes file: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise InputError(f"{p}: not valid YAML: {str(exc).splitlines()[0]}") from None
    block = data.get("detect", data) if isinstance(data, dict) else None
    block = block.get("classes") if isinstance(block, dict) else None
    if not isinstance(block, dict):
        raise InputError(f"{p}: field 'detect.classes' is missing or not a mapping")
    roles: dict[str, tuple[int, ...]] = {}
    for role in ROLES:
        codes = block.get(role)
        if isinstance(codes, int) and not isinstance(codes, bool):
            codes = [codes]
        if not (isinstance(codes, list) and codes and all(_is_code(c) for c in codes)):
            raise InputError(
                f"{p}: field 'detect.classes.{role}' must be a non-empty list of codes 0-255, "
                f"got {codes!r}"
            )
        roles[role] = tuple(int(c) for c in codes)
    unknown = sorted(set(block) - set(ROLES))
    if unknown:
        raise InputError(f"{p}: field 'detect.classes.{unknown[0]}' is not a role ({ROLES})")
    return ClassScheme(p.stem, roles, {})


def scheme(spec: str) -> ClassScheme | None:
    """The scheme named ``spec`` (:data:`SCHEMES`), None for ``unclassified``, else a YAML
    file's (:func:`load_scheme`)."""
    if spec in SCHEMES:
        return SCHEMES[spec]
    if spec == UNCLASSIFIED:
        return None
    if spec.endswith((".yaml", ".yml")) or Path(spec).exists():
        return load_scheme(spec)
    raise InputError(
        f"class_codes = {spec!r} must be one of {', '.join([*SCHEMES, UNCLASSIFIED])} "
        "or a YAML file with detect: classes:"
    )


@dataclass(frozen=True)
class StreetKind:
    """How a synthetic street is seen and written (see the module docstring)."""

    path: str = "vehicle"
    plain: bool = False
    colour: bool = True
    density: float = 1.0
    point_spacing_m: float | None = None
    class_codes: str | None = None

    def __post_init__(self) -> None:
        if self.path not in PATHS:
            raise InputError(f"path = {self.path!r} must be one of {', '.join(PATHS)}")
        if not (math.isfinite(self.density) and 0.0 < self.density <= 1.0):
            raise InputError(f"density = {self.density} must be a fraction in (0, 1]")
        s = self.point_spacing_m
        if s is not None and not (math.isfinite(s) and 0.01 <= s <= 5.0):
            raise InputError(f"point_spacing_m = {s} must be in [0.01, 5] m")
        if self.class_codes is not None:
            scheme(self.class_codes)  # fails early with the field named

    @property
    def is_default(self) -> bool:
        return self == StreetKind()

    def scheme(self) -> ClassScheme | None:
        """The written coding; None when every point is written as unclassified."""
        return SCHEMES["streetcd"] if self.class_codes is None else scheme(self.class_codes)

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


PRESETS: dict[str, StreetKind] = {
    "default": StreetKind(),
    "pedestrian": StreetKind(path="sidewalk-right"),
    "pedestrian-left": StreetKind(path="sidewalk-left"),
    "plain": StreetKind(plain=True),
    "no-colour": StreetKind(colour=False),
    "sparse": StreetKind(density=0.1),
    "codes": StreetKind(class_codes="city"),
    "asprs": StreetKind(class_codes="asprs"),
    "unclassified": StreetKind(class_codes=UNCLASSIFIED),
    # the other renderer's street of issue 16: plain objects in front of plain walls, seen
    # obliquely from the far sidewalk, a sparse cloud without colours, ASPRS codes
    "mixed": StreetKind(
        path="sidewalk-right", plain=True, colour=False, density=0.25, class_codes="asprs"
    ),
}

PRESET_HELP = {
    "default": "today's street: vehicle path, textured objects, dense coloured cloud",
    "pedestrian": "pedestrian on the near sidewalk looking obliquely across (far side at 10-20 m)",
    "pedestrian-left": "pedestrian on the far sidewalk looking along the street",
    "plain": "uniformly painted objects, some ~1 m in front of plain walls",
    "no-colour": "cloud without RGB (LAS point format 6)",
    "sparse": "a tenth of the points",
    "codes": "a city's class codes (several per role) + streetcd.yaml",
    "asprs": "ASPRS codes below 32 (poles 15, signs 19, ...) + streetcd.yaml",
    "unclassified": "every point class 1",
    "mixed": "pedestrian, plain, no colour, a quarter of the points, ASPRS codes",
}


def resolve_kind(kind: str | StreetKind | None = None, **overrides: Any) -> StreetKind:
    """The preset ``kind`` (a name of :data:`PRESETS`, a :class:`StreetKind`, or None for
    the default) with the settings in ``overrides`` that are not None put over it."""
    if kind is None:
        base = StreetKind()
    elif isinstance(kind, StreetKind):
        base = kind
    elif kind in PRESETS:
        base = PRESETS[kind]
    else:
        raise InputError(f"kind = {kind!r} must be one of {', '.join(PRESETS)}")
    given = {k: v for k, v in overrides.items() if v is not None}
    unknown = sorted(set(given) - {f.name for f in fields(StreetKind)})
    if unknown:
        raise InputError(f"{unknown[0]!r} is not a street kind setting")
    return replace(base, **given) if given else base
