"""The cloud's class codes read as the roles the method needs (not in the paper, which had
one scanner's classes): a city's codes are mapped by the config's class map
(:class:`streetcd.config.ClassMap`) to streetcd's codes (:data:`streetcd.classes.ROLES`)
before the z-buffer, so that every later step (the low-weight classes of eq. 5, the class
term of eq. 11, the inventory of the appearance and texture cues) reads one coding.
"""

from __future__ import annotations

import functools

import numpy as np

from streetcd import classes
from streetcd.config import ClassMap

# Below this share of points in a role other than the ground and the road, a cloud's classes
# tell the detector nothing it uses: the class term and the class weights fall away.
MIN_USEFUL_SHARE = 0.01


@functools.lru_cache(maxsize=8)
def _table(class_map: ClassMap) -> np.ndarray:
    return np.asarray(class_map.table(), np.uint8)


def role_codes(classification: np.ndarray, class_map: ClassMap) -> np.ndarray:
    """(N,) uint8 cloud codes → (N,) uint8 streetcd codes; codes in no role become
    :data:`streetcd.classes.UNCLASSIFIED`."""
    return _table(class_map)[np.asarray(classification, np.uint8)]


def useless_classes(classification: np.ndarray, class_map: ClassMap) -> str | None:
    """Why the classes of a cloud (N,) uint8 (its own codes) are of no use to the detector,
    or None when they are: fewer than ``MIN_USEFUL_SHARE`` of the points are in a role
    besides the ground and the road (an unclassified cloud, or codes the class map lacks)."""
    counts = np.bincount(np.asarray(classification, np.uint8), minlength=256)
    total = int(counts.sum())
    if total == 0:
        return None
    table = _table(class_map)
    plain = (classes.UNCLASSIFIED, classes.GROUND, classes.ROAD)
    useful = int(counts[~np.isin(table, plain)].sum())
    if useful >= MIN_USEFUL_SHARE * total:
        return None
    top = ", ".join(
        f"{code}: {100 * counts[code] / total:.1f} %"
        for code in np.argsort(counts)[::-1][:4]
        if counts[code]
    )
    return (
        f"only {100 * useful / total:.2f} % of the reference points have a class the detector "
        f"uses (vegetation, building, pole, sign, railing, furniture, vehicle; codes by share: "
        f"{top}): set detect.classes in the config to the cloud's own codes, or expect more "
        "false alarms on trees and roads"
    )
