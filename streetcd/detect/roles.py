"""The cloud's class codes read as the roles the method needs (not in the paper, which had
one scanner's classes): a city's codes are mapped by the config's class map
(:class:`streetcd.config.ClassMap`) to streetcd's codes (:data:`streetcd.classes.ROLES`)
before the z-buffer, so that every later step (the low-weight classes of eq. 5, the class
term of eq. 11, the inventory of the appearance and texture cues) reads one coding.

Points in no role take a role inferred from the cloud's geometry
(:mod:`streetcd.detect.infer_roles`) when the class map's ``infer`` asks for it: ``"auto"``
when the cloud's classes are of no use (:func:`useless_classes`), ``"always"`` whatever they
are. The inference runs once per cloud (a per-segment crop is shared by its views).
"""

from __future__ import annotations

import functools
import logging
import time
import weakref
from collections.abc import Sequence

import cv2
import numpy as np

from streetcd import classes
from streetcd.config import ClassMap
from streetcd.detect.infer_roles import infer_roles
from streetcd.detect.memo import ArrayMemo

log = logging.getLogger(__name__)
# the cloud's xyz → its inferred roles, kept while the cloud lives
_INFERRED = ArrayMemo()
# the cloud's classification → {(class map, id of its xyz): (xyz, roles)}: every surface of a
# cloud (the view's and its neighbours') reads the same roles; mapping and checking a
# 2-million-point cloud once per surface cost ~80 ms of a 2 MP view (docs/BENCHMARKS.md)
_ROLES = ArrayMemo()
# the cloud's classification → its points per code: the class checks and the roles read them
# four times per cloud (a bincount of 3 million points is ~4.5 ms; docs/BENCHMARKS.md)
_COUNTS = ArrayMemo()

# Below this share of points in a role other than the ground and the road, a cloud's classes
# tell the detector nothing it uses: the class term and the class weights fall away.
MIN_USEFUL_SHARE = 0.01
# Above this share of points in no role, "auto" infers those points' roles although the rest
# are classified: a cloud mostly unclassified, with a few classified objects in it, is read
# like an unclassified one (its ground keeps the low weight of eq. 5; docs/TUNING.md,
# sixteenth round).
MAX_ROLELESS_SHARE = 0.5


def in_roles(raster: np.ndarray, codes: Sequence[int]) -> np.ndarray:
    """(H, W) bool: the pixels of the (H, W) uint8 role raster whose code is in ``codes``.

    The same as ``np.isin(raster, codes)`` through one 256-entry look-up table (OpenCV's):
    np.isin sorts and searches, ~1 ms per call at 2 MP, and a view asks this five times."""
    table = np.zeros(256, np.uint8)
    table[np.asarray(codes, np.int64)] = 1
    raster = np.ascontiguousarray(raster, np.uint8)
    if raster.size == 0:  # OpenCV returns None for an empty array
        return np.zeros(raster.shape, bool)
    return cv2.LUT(raster, table).view(bool)


@functools.lru_cache(maxsize=8)
def _table(class_map: ClassMap) -> np.ndarray:
    return np.asarray(class_map.table(), np.uint8)


def role_codes(classification: np.ndarray, class_map: ClassMap) -> np.ndarray:
    """(N,) uint8 cloud codes → (N,) uint8 streetcd codes; codes in no role become
    :data:`streetcd.classes.UNCLASSIFIED`."""
    codes = np.ascontiguousarray(classification, np.uint8)
    if codes.size == 0:  # OpenCV returns None for an empty array
        return codes.copy()
    # OpenCV's table look-up: the same values as numpy's indexing, 8 times faster
    return cv2.LUT(codes.reshape(-1, 1), _table(class_map)).reshape(codes.shape)


def cloud_roles(xyz: np.ndarray, classification: np.ndarray, class_map: ClassMap) -> np.ndarray:
    """(N,) uint8 streetcd codes of a cloud's points: ``classification`` (N,) uint8 (its own
    codes) through the class map, and, where ``class_map.infer`` says so, the points in no
    role given the role :func:`~streetcd.detect.infer_roles.infer_roles` finds from ``xyz``
    (N, 3) metres. The roles are computed once per ``classification`` and ``xyz`` array (they
    must not change in place while they live) and kept with them; the array returned is
    read-only."""
    kept: dict = _ROLES.get(classification, lambda _: {})
    hit = kept.get((class_map, id(xyz)))
    if hit is not None and hit[0]() is xyz:
        return hit[1]
    roles = _roles(xyz, classification, class_map)
    roles.flags.writeable = False
    for key in [k for k, (ref, _) in kept.items() if ref() is None]:
        del kept[key]  # an xyz array gone (one classification array seen with several)
    kept[class_map, id(xyz)] = (weakref.ref(xyz), roles)
    return roles


def _roles(xyz: np.ndarray, classification: np.ndarray, class_map: ClassMap) -> np.ndarray:
    """:func:`cloud_roles` computed (a new, writeable array)."""
    roles = role_codes(classification, class_map)
    if not infers(classification, class_map):
        return roles
    unclassified = roles == classes.UNCLASSIFIED
    if unclassified.any():
        roles[unclassified] = _INFERRED.get(xyz, _timed_inference)[unclassified]
    return roles


def infers(classification: np.ndarray, class_map: ClassMap) -> bool:
    """Whether :func:`cloud_roles` infers the roles of a cloud of these classes (N,) uint8."""
    return infers_codes(_code_counts(classification)[0], class_map)


def infers_codes(counts: np.ndarray, class_map: ClassMap) -> bool:
    """:func:`infers` of points counted by code, ``counts`` (256,)."""
    if class_map.infer == "off" or int(np.sum(counts)) == 0:
        return False
    if class_map.infer == "always" or useless_codes(counts, class_map) is not None:
        return True
    return roleless_codes(counts, class_map) is not None


def road_told(classification: np.ndarray, class_map: ClassMap) -> bool:
    """Whether a cloud of these classes (N,) uint8 (its own codes) tells its road from its
    ground: at least ``MIN_USEFUL_SHARE`` of its points are road and no role is inferred
    (:func:`~streetcd.detect.infer_roles.infer_roles` gives the road and the sidewalk one
    role). Only then does the reference-colour check look at the ground
    (``AppearanceParams.ground_classes``): on the road, cars come and go."""
    return road_told_codes(_code_counts(classification)[0], class_map) is None


def road_told_codes(counts: np.ndarray, class_map: ClassMap) -> str | None:
    """Why a cloud whose points are counted by code, ``counts`` (256,), does not tell its road
    from its ground (:func:`road_told`), or None when it does."""
    counts = np.asarray(counts)
    total = int(counts.sum())
    if total == 0:
        return "the cloud has no points"
    if infers_codes(counts, class_map):
        return (
            "the points' roles are inferred from their geometry, which gives the road and the"
            " sidewalk one role"
        )
    road = int(counts[_table(class_map) == classes.ROAD].sum())
    if road < MIN_USEFUL_SHARE * total:
        return f"only {100 * road / total:.2f} % of the points are road (detect.classes road)"
    return None


def _timed_inference(xyz: np.ndarray) -> np.ndarray:
    start = time.perf_counter()
    roles = infer_roles(xyz)
    log.info(
        "roles of %d points inferred from the geometry in %.2f s (detect.classes.infer)",
        len(roles),
        time.perf_counter() - start,
    )
    return roles


def useless_classes(classification: np.ndarray, class_map: ClassMap) -> str | None:
    """Why the classes of a cloud (N,) uint8 (its own codes) are of no use to the detector,
    or None when they are: fewer than ``MIN_USEFUL_SHARE`` of the points are in a role
    besides the ground and the road (an unclassified cloud, or codes the class map lacks)."""
    return useless_codes(_code_counts(classification)[0], class_map)


def useless_codes(counts: np.ndarray, class_map: ClassMap) -> str | None:
    """:func:`useless_classes` of points counted by code: ``counts`` (256,) points per code
    of the cloud's own (``streetcd check`` counts the store's tiles near the views)."""
    counts = np.asarray(counts)
    total = int(counts.sum())
    if total == 0:
        return None
    table = _table(class_map)
    plain = (classes.UNCLASSIFIED, classes.GROUND, classes.ROAD)
    useful = int(counts[~np.isin(table, plain)].sum())
    if useful >= MIN_USEFUL_SHARE * total:
        return None
    meanwhile = (
        "expect more false alarms on trees and roads"
        if class_map.infer == "off"
        else "meanwhile the roles are inferred from the points' geometry (detect.classes.infer)"
    )
    return (
        f"only {100 * useful / total:.2f} % of the reference points have a class the detector "
        f"uses (vegetation, building, pole, sign, railing, furniture, vehicle; codes by share: "
        f"{_top_codes(counts)}): set detect.classes in the config to the cloud's own codes; "
        f"{meanwhile}"
    )


def mostly_roleless(classification: np.ndarray, class_map: ClassMap) -> str | None:
    """Why the roles of most of a cloud's points (N,) uint8 (its own codes) are missing: more
    than ``MAX_ROLELESS_SHARE`` of them have a code in no role of the class map; None when
    fewer do. With ``infer: auto`` those points' roles are then inferred."""
    return roleless_codes(_code_counts(classification)[0], class_map)


def roleless_codes(counts: np.ndarray, class_map: ClassMap) -> str | None:
    """:func:`mostly_roleless` of points counted by code, ``counts`` (256,)."""
    counts = np.asarray(counts)
    total = int(counts.sum())
    roleless = int(counts[_table(class_map) == classes.UNCLASSIFIED].sum())
    if total == 0 or roleless <= MAX_ROLELESS_SHARE * total:
        return None
    meanwhile = (
        "they count as unclassified (detect.classes.infer is off)"
        if class_map.infer == "off"
        else "their roles are inferred from the points' geometry (detect.classes.infer)"
    )
    return (
        f"{100 * roleless / total:.1f} % of the reference points have a code in no role of "
        f"detect.classes (codes by share: {_top_codes(counts)}): {meanwhile}"
    )


def role_of_code(code: int, class_map: ClassMap) -> str | None:
    """The name of the role the class map gives a cloud's code (0-255); None for none."""
    role = int(_table(class_map)[code])
    return None if role == classes.UNCLASSIFIED else classes.NAMES.get(role, str(role))


def _code_counts(classification: np.ndarray) -> tuple[np.ndarray, int]:
    """(256,) points per class code of a cloud's classification (N,) uint8 (read-only; kept
    while the array lives, which must not change in place meanwhile), and N."""
    if not isinstance(classification, np.ndarray):
        return _counted(np.asarray(classification))
    counted: tuple[np.ndarray, int] = _COUNTS.get(classification, _counted)
    return counted


def _counted(classification: np.ndarray) -> tuple[np.ndarray, int]:
    counts = np.bincount(np.asarray(classification, np.uint8).ravel(), minlength=256)
    counts.flags.writeable = False
    return counts, int(counts.sum())


def _top_codes(counts: np.ndarray) -> str:
    """The four commonest codes of (256,) counts with their shares, as text."""
    total = int(counts.sum())
    return ", ".join(
        f"{code}: {100 * counts[code] / total:.1f} %"
        for code in np.argsort(counts)[::-1][:4]
        if counts[code]
    )
