"""Point classes used throughout streetcd: ASPRS LAS 1.4 codes where the standard has one,
user-definable codes (64-255) for the street objects it does not name.

Classification is stored per point as ``uint8``; rasters of classes use the same codes.
"""

from __future__ import annotations

UNCLASSIFIED = 1
GROUND = 2  # bare ground, sidewalks, verges
VEGETATION = 5  # ASPRS "high vegetation": trees and hedges
BUILDING = 6  # façades
ROAD = 11  # ASPRS "road surface"
POLE = 64  # street-light poles, sign posts
SIGN = 65  # signs and boards (thin planar objects)
RAILING = 66  # railings and fences
FURNITURE = 67  # benches, bins
CAR = 68  # parked vehicles
PEDESTRIAN = 69  # never in a cleaned reference cloud; used by the synthetic ground truth

NAMES: dict[int, str] = {
    UNCLASSIFIED: "unclassified",
    GROUND: "ground",
    VEGETATION: "vegetation",
    BUILDING: "building",
    ROAD: "road",
    POLE: "pole",
    SIGN: "sign",
    RAILING: "railing",
    FURNITURE: "furniture",
    CAR: "car",
    PEDESTRIAN: "pedestrian",
}

# Classes whose raw change the detector down-weights (paper §3.3: "a small weight to the raw
# changes that reside in the class of the trees and roads"). We add the ground (sidewalks,
# verges) for the paper's reason for roads: a car parked since the scan hides the kerb and
# the sidewalk from the neighbours that the view sees past it, and a patch of sidewalk
# between two cars became change (docs/TUNING.md). Objects standing on the ground keep their
# full weight where the old surface behind them is a wall, a pole or a sign.
LOW_WEIGHT = (VEGETATION, ROAD, GROUND)

# Classes whose reference colours the appearance check compares with the image
# (:mod:`streetcd.detect.appearance`): the street inventory a city keeps, where "is the object
# still there?" is the question, and where a removed or replaced object often leaves no
# geometric trace a neighbour can see (a board in front of a plain wall, a hedge in place of
# a railing).
INVENTORY = (POLE, SIGN, RAILING, FURNITURE)

# The roles the method needs, by name, and the code each has inside streetcd. A cloud's own
# codes are mapped to these by the config's class map (``detect.classes``,
# :class:`streetcd.config.ClassMap`) before detection; the code lists of the detector's
# settings (``correlate.low_weight_classes``, ``appearance.classes``, ``texture.classes``)
# name roles by these codes.
ROLES: dict[str, int] = {
    "ground": GROUND,
    "road": ROAD,
    "vegetation": VEGETATION,
    "building": BUILDING,
    "pole": POLE,
    "sign": SIGN,
    "railing": RAILING,
    "furniture": FURNITURE,
    "vehicle": CAR,
}
