"""One frozen :class:`Config`: the detector's parameters (``detect``) and the nightly run's
(``run``), defaults from the paper (Table 3 and text) where it gives them.

Pixel-sized parameters are given for the paper's images (16 MP, about 4900 px wide) at
``REFERENCE_WIDTH_PX`` and scaled with the image width by :func:`scale_px`; the paper itself
says the edge threshold "varies according to the image resolution" (Table 3).

Loaded from YAML (``configs/default.yaml``, whose header says which values are the paper's
and which are our additions) only at the edges, with :func:`load_config`. Every setting lives
in one place: the number of neighbours per view, for one, is ``detect.correlate.n_neighbours``
for ``streetcd detect`` and the nightly run alike. :meth:`Config.results_hash` covers exactly
the settings that change a run's results, so the next night re-detects a view only when one
of them changed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from streetcd import classes
from streetcd.classes import BUILDING, FURNITURE, GROUND, RAILING, SIGN, VEGETATION
from streetcd.errors import InputError

REFERENCE_WIDTH_PX = 4000


def scale_px(value_px: float, width_px: int, minimum: float = 1.0) -> float:
    """A pixel length given at ``REFERENCE_WIDTH_PX`` scaled to an image ``width_px`` wide."""
    return max(minimum, value_px * width_px / REFERENCE_WIDTH_PX)


def _check(cond: bool, name: str, value: Any, rule: str) -> None:
    if not cond:
        raise InputError(f"parameter {name} = {value!r} must be {rule}")


def _codes(obj: Any, name: str, field_name: str) -> None:
    """Check that ``obj.<field_name>`` is a list of class codes (integers 0-255, not
    booleans; a code out of range fails at load, not later in a 256-entry look-up) and store
    it as a tuple."""
    values = getattr(obj, field_name)
    ok = isinstance(values, tuple | list) and all(type(c) is int and 0 <= c <= 255 for c in values)
    _check(ok, name, list(values) if isinstance(values, tuple | list) else values, "codes 0-255")
    object.__setattr__(obj, field_name, tuple(values))


@dataclass(frozen=True)
class ZBufferParams:
    """Block-window (eq. 1) and weighted-window (eq. 2–3) z-buffer, paper §3.2."""

    block_window_px: int = 5  # w, eq. 1
    weighted_window_px: int = 15  # w1, eq. 2
    gamma_px: float = 100.0  # γ, 2D proximity scale of eq. 2
    delta_color: float = 10.0  # δ, colour proximity scale of eq. 2 (8-bit RGB)
    tau: float = 0.5  # τ, support threshold on W(p)
    max_angle_deg: float = 45.0  # θ threshold of eq. 3
    scale_with_resolution: bool = False  # windows are point-density driven, not resolution
    # s, metres: the cloud's widest point spacing (0.12 m: one scanner's profile spacing on the
    # synthetic streets); > 0 widens w1 around near points to their projected spacing f·s/z
    # (see streetcd.detect.zbuffer); 0 keeps the paper's fixed w1
    point_spacing_m: float = 0.12
    # our addition (issue 16): > 0 takes s per point as max(point_spacing_m, this × the
    # cloud's measured spacing of its class, streetcd.detect.spacing), so a sparse cloud's
    # near surfaces still hide what lies behind them; 0 = point_spacing_m alone. 4: a dense
    # MLS cloud (≤ 0.03 m) stays at 0.12 m, a sparse one widens (docs/DECISIONS.md)
    spacing_factor: float = 4.0
    # our addition (issue 16): false drops eq. 2's colour term for a supporter that only the
    # cloud's own sparser spacing reaches (farther than max(w1 / 2, f · point_spacing_m / z)):
    # on a sparse near object the image's colours 50 px apart are not alike, and the wall
    # behind it stayed visible. Part of the sparse-cloud defaults (docs/TUNING.md,
    # seventeenth round); a dense cloud is the same either way (true: the colour term
    # everywhere, the paper)
    reach_colour: bool = False

    def __post_init__(self) -> None:
        _check(self.block_window_px >= 1, "block_window_px", self.block_window_px, ">= 1")
        _check(self.weighted_window_px >= 1, "weighted_window_px", self.weighted_window_px, ">= 1")
        _check(self.gamma_px > 0, "gamma_px", self.gamma_px, "> 0")
        _check(self.delta_color > 0, "delta_color", self.delta_color, "> 0")
        _check(0 < self.tau < 1, "tau", self.tau, "in (0, 1)")
        _check(0 < self.max_angle_deg < 90, "max_angle_deg", self.max_angle_deg, "in (0, 90)")
        _check(
            math.isfinite(self.point_spacing_m) and self.point_spacing_m >= 0,
            "point_spacing_m",
            self.point_spacing_m,
            ">= 0",
        )
        _check(
            math.isfinite(self.spacing_factor) and self.spacing_factor >= 0,
            "spacing_factor",
            self.spacing_factor,
            ">= 0",
        )


@dataclass(frozen=True)
class SurfaceParams:
    """View-dependent triangulation and rasters, paper §3.3 (first paragraph)."""

    max_depth_jump_m: float = 0.5  # triangles spanning more depth than this are dropped
    max_edge_px: float = 30.0  # at REFERENCE_WIDTH_PX; scaled with the image width
    # our addition (issue 16): > 0 lets a triangle's edges reach this many projected point
    # spacings f·s/z (s: the cloud's measured spacing of a vertex's class,
    # streetcd.detect.spacing) where that exceeds max_edge_px: sparse clouds keep a surface.
    # 8, with spacing_edge_min_spacing_m 0.04 (dense clouds keep the paper's limit) and
    # spacing_edge_same_role (docs/TUNING.md, seventeenth round); 0 = the fixed limit alone
    spacing_edge_factor: float = 8.0
    # our addition (issue 16): > 0 lets a triangle span this many s in depth where that
    # exceeds max_depth_jump_m (s of its densest vertex); 0 = the fixed jump alone. 10: a
    # dense MLS cloud (≤ 0.03 m) stays at 0.5 m
    spacing_jump_factor: float = 10.0
    # our addition (issue 16): the edge widening leaves alone every triangle with a vertex
    # nearer than this (metres, camera z): near the camera f·s/z reaches hundreds of px and
    # bridges the ground a vehicle rig's own body hides; 0 = no floor
    spacing_edge_min_depth_m: float = 0.0
    # our addition (issue 16): points whose class is measured denser than this (metres)
    # never widen edges: max_edge_px already suits a mobile-mapping cloud (≤ 0.03 m), where a
    # longer edge only bridges a real gap; 0 = every class
    spacing_edge_min_spacing_m: float = 0.04
    # our addition (issue 16): points whose class is measured sparser than this (metres)
    # never widen edges: a dense mobile-mapping cloud seen from near (a pedestrian's camera,
    # 2-5 m from the objects) widens, a sparse automotive LiDAR keeps the fixed limit; 0 = no cut
    spacing_edge_max_spacing_m: float = 0.0
    # our addition (issue 16): roles whose points may widen edges (streetcd.classes codes;
    # a triangle widens only if all its vertices do); () = every role
    spacing_edge_classes: tuple[int, ...] = ()
    # our addition (issue 16): a triangle longer than max_edge_px is kept only when its three
    # vertices have one role: widening bridges the gaps of one sparsely sampled surface, not
    # the step from an object to the ground or the wall behind it (docs/TUNING.md,
    # seventeenth round); False = any roles
    spacing_edge_same_role: bool = True
    # our addition (issue 16): the near points of these roles fill their object's surface
    # between them. A pole 1-3 m from the camera, scanned in profiles 40-70 px apart there,
    # gets no triangle under max_edge_px and the wall behind it showed through its outline.
    # Each point stands for a disc of point_fill_reach x its z-buffer reach f·s/z
    # (streetcd.detect.zbuffer), and a pixel is filled only where it lies point_fill_core x
    # its disc's radius inside their union (a closing: nothing spills past the outer points).
    # Railings are left out: their gaps show what is behind. Points whose disc's radius is
    # under point_fill_min_px are left to the triangles, and a cloud whose roles are inferred
    # from its geometry is not filled: an inferred pole may be anything upright
    # (docs/TUNING.md, thirty-first round); () = off (the paper)
    point_fill_classes: tuple[int, ...] = (classes.POLE, classes.SIGN, classes.FURNITURE)
    point_fill_reach: float = 0.6
    point_fill_core: float = 0.9
    point_fill_min_px: float = 3.0

    def __post_init__(self) -> None:
        _check(self.max_depth_jump_m > 0, "max_depth_jump_m", self.max_depth_jump_m, "> 0")
        _check(self.max_edge_px > 0, "max_edge_px", self.max_edge_px, "> 0")
        _codes(self, "point_fill_classes", "point_fill_classes")
        _check(self.point_fill_reach > 0, "point_fill_reach", self.point_fill_reach, "> 0")
        _check(0 < self.point_fill_core <= 1, "point_fill_core", self.point_fill_core, "in (0, 1]")
        _check(self.point_fill_min_px >= 0, "point_fill_min_px", self.point_fill_min_px, ">= 0")
        for name in (
            "spacing_edge_factor",
            "spacing_jump_factor",
            "spacing_edge_min_depth_m",
            "spacing_edge_min_spacing_m",
            "spacing_edge_max_spacing_m",
        ):
            value = getattr(self, name)
            _check(math.isfinite(value) and value >= 0, name, value, ">= 0")
        _codes(self, "spacing_edge_classes", "spacing_edge_classes")


@dataclass(frozen=True)
class CorrelateParams:
    """Neighbour re-projection and raw change (eq. 4–5), paper §3.3."""

    n_neighbours: int = 3  # the paper uses 2–3 overlapping views
    # [ours] px at REFERENCE_WIDTH_PX: neighbours are ranked by overlap × min(1, parallax at
    # 20 m / this), so a camera that did not move is never one (0 = overlap alone, the paper)
    min_parallax_px: float = 16.0
    occlusion_tolerance_m: float = 0.3  # a pixel is occluded in q if q sees something closer
    stretch_percentiles: tuple[float, float] = (1.0, 99.0)  # histogram stretching per view
    low_weight_classes: tuple[int, ...] = classes.LOW_WEIGHT  # trees, roads (paper), ground
    low_class_weight: float = 0.2  # "a small weight" for those classes
    # colour tolerance for registration error: p's colour is compared with the range of q's
    # colours within this radius (px at REFERENCE_WIDTH_PX; 0 = the paper's pixel difference)
    registration_tolerance_px: float = 4.0  # tuned, docs/TUNING.md (2 px at 1920 wide)
    # [ours] ... and never less than this many of the image's own pixels (a pose's error as a
    # reprojection error, a pixel or two at any resolution); 0 = the scaled radius alone, the
    # default: 2 quiets every unchanged validation street but loses on the mixed kind
    registration_floor_px: float = 0.0  # docs/TUNING.md, twenty-second round
    # > 0: pixels within f·m/z px of a nearer surface at depth z are also tested at that
    # depth (the unscanned side of near poles, streetcd.detect.silhouette); 0 = the paper's method
    silhouette_margin_m: float = 0.2  # tuned, docs/TUNING.md
    # [ours] > 0: that band ends at the near object's outline in the view (no edge of the
    # view's grey levels, Canny with this upper threshold and half of it as the lower, between
    # a pixel and the near surface): a new pole standing beside a near column keeps its
    # evidence; 0 = the reach alone
    silhouette_edge_threshold: float = 120.0  # docs/TUNING.md, twenty-fourth round
    # [ours] each neighbour is registered to the view by the whole-image shift, up to this
    # (px at REFERENCE_WIDTH_PX), that best correlates it, warped through the old surface,
    # with the view (streetcd.detect.align); 0 = the poses as given (the paper)
    align_shift_px: float = 32.0  # docs/TUNING.md, twenty-fifth round
    # [ours] ... kept only where it correlates better than no shift by this much
    align_min_gain: float = 0.05
    # True: each neighbour's levels are fitted to the view's on the pixels they share
    # (streetcd.detect.correlate.pair_lut); False: each image stretched on its own (the paper)
    pair_gain: bool = True
    # holes in q's surface within this distance (px at REFERENCE_WIDTH_PX) of its surface take
    # the nearest-by minimum depth for the occlusion test (streetcd.detect.correlate.hole_depths:
    # near poles leave holes between their sparse points); 0 = holes hide nothing (the paper)
    occluder_fill_px: float = 120.0
    # [ours] eq. 5's C_p is the second-smallest of the neighbours' differences where three or
    # more of them see the pixel (two agreeing neighbours, not one, must explain it: one that
    # matches by chance, moving along its line of sight or over a plain background, no longer
    # hides what the others see); False = the minimum everywhere (the paper)
    second_smallest: bool = True  # docs/TUNING.md, twenty-first round
    # [ours] ... but where the cloud has colours, only where the view's colour differs from the
    # old cloud's (the reference-colour check's distance after its colour transfer, within the
    # registration radius) by at least this; elsewhere the minimum: the old surface is what the
    # view shows, and two neighbours that disagree there see something new in front of it
    # (0 = no gate)
    second_smallest_gate: float = 0.15  # docs/TUNING.md, twenty-third round
    # our addition (issue 16): the nearer-depth test (streetcd.detect.sweep): the fused change
    # is also max(..., nearer_weight · N_p), N_p how much better a depth in front of the old
    # surface explains the view and its neighbours (added objects); 0 = off, the default: on
    # the validation set it gains at full size and loses at 1280 × 720 (docs/TUNING.md)
    nearer_weight: float = 0.0
    nearer_fractions: tuple[float, ...] = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
    nearer_margin: float = 0.05  # colour distance (0-1) the nearer depth must gain ...
    nearer_span: float = 0.15  # ... and beyond it, this much more for N_p = 1
    nearer_match: float = 0.08  # ... and explain the pixel: its worst distance at most this
    nearer_window_px: int = 5  # colours averaged over this square at the working scale
    nearer_scale: float = 0.5  # the test runs at this fraction of the image's resolution

    def __post_init__(self) -> None:
        _codes(self, "low_weight_classes", "low_weight_classes")
        _check(self.n_neighbours >= 1, "n_neighbours", self.n_neighbours, ">= 1")
        _check(self.nearer_weight >= 0, "nearer_weight", self.nearer_weight, ">= 0")
        _check(
            all(0 < f < 1 for f in self.nearer_fractions),
            "nearer_fractions",
            self.nearer_fractions,
            "fractions in (0, 1)",
        )
        object.__setattr__(self, "nearer_fractions", tuple(float(f) for f in self.nearer_fractions))
        _check(self.nearer_span > 0, "nearer_span", self.nearer_span, "> 0")
        _check(self.nearer_match >= 0, "nearer_match", self.nearer_match, ">= 0")
        _check(self.nearer_window_px >= 1, "nearer_window_px", self.nearer_window_px, ">= 1")
        _check(0 < self.nearer_scale <= 1, "nearer_scale", self.nearer_scale, "in (0, 1]")
        _check(self.min_parallax_px >= 0, "min_parallax_px", self.min_parallax_px, ">= 0")
        _check(self.occluder_fill_px >= 0, "occluder_fill_px", self.occluder_fill_px, ">= 0")
        _check(
            math.isfinite(self.silhouette_edge_threshold) and self.silhouette_edge_threshold >= 0,
            "silhouette_edge_threshold",
            self.silhouette_edge_threshold,
            "a finite number >= 0",
        )
        lo, hi = self.stretch_percentiles
        _check(
            0 <= lo < hi <= 100,
            "stretch_percentiles",
            self.stretch_percentiles,
            "0 <= lo < hi <= 100",
        )
        _check(
            0 <= self.low_class_weight <= 1, "low_class_weight", self.low_class_weight, "in [0, 1]"
        )
        _check(
            self.silhouette_margin_m >= 0,
            "silhouette_margin_m",
            self.silhouette_margin_m,
            ">= 0",
        )
        _check(
            self.registration_tolerance_px >= 0,
            "registration_tolerance_px",
            self.registration_tolerance_px,
            ">= 0",
        )
        _check(
            0 <= self.second_smallest_gate <= 1,
            "second_smallest_gate",
            self.second_smallest_gate,
            "in [0, 1]",
        )
        _check(self.align_shift_px >= 0, "align_shift_px", self.align_shift_px, ">= 0")
        _check(-1 <= self.align_min_gain <= 2, "align_min_gain", self.align_min_gain, "in [-1, 2]")
        _check(
            self.registration_floor_px >= 0,
            "registration_floor_px",
            self.registration_floor_px,
            ">= 0",
        )


@dataclass(frozen=True)
class GraphCutParams:
    """Node energy (eq. 7), class-aware SLIC (eq. 10–11), graph cut (eq. 6, 8–9), speckle."""

    a: float = 45.0  # steepness of the S-curve of eq. 7
    b: float = 11.0  # shift of the S-curve of eq. 7
    beta: float = 10.0  # β of eq. 6, weight of the smoothness term (tuned, docs/TUNING.md)
    superpixel_cell_px: float = 50.0  # SLIC cell size S at REFERENCE_WIDTH_PX
    superpixel_work_cell_px: float = 12.0  # SLIC runs downscaled to about this cell size
    compactness: float = 20.0  # M/S of eq. 10
    class_penalty: float = 400.0  # α of eq. 11
    color_scale: float = 10.0  # colour distance (8-bit RGB) that makes exp(−·) = 1/e, eq. 8
    depth_scale_m: float = 1.0  # depth difference that makes exp(−·) = 1/e, eq. 8 (tuned)
    use_color: bool = True  # ablation switches for the similarity terms of eq. 8
    use_depth: bool = True
    use_class: bool = True
    speckle_min_px: int = 200  # segments smaller than this are removed (at reference width)
    # our reading of the paper's superpixel speed-up (issue 16): a superpixel's node energy is
    # eq. 7 of its mean raw change ("for each superpixel, the color value and depth value are
    # assigned as the average value over all the pixels"), not the mean of its pixels' eq. 7:
    # a weak change that holds over a whole object is not flattened by the S-curve pixel by
    # pixel, and a few stray pixels of high change weigh less. False: the mean of eq. 7
    energy_of_mean: bool = False

    def __post_init__(self) -> None:
        _check(self.a > 0, "a", self.a, "> 0")
        _check(self.beta >= 0, "beta", self.beta, ">= 0")
        _check(self.superpixel_cell_px >= 2, "superpixel_cell_px", self.superpixel_cell_px, ">= 2")
        _check(
            self.superpixel_work_cell_px >= 2,
            "superpixel_work_cell_px",
            self.superpixel_work_cell_px,
            ">= 2",
        )
        _check(self.compactness > 0, "compactness", self.compactness, "> 0")
        _check(self.class_penalty >= 0, "class_penalty", self.class_penalty, ">= 0")
        _check(self.color_scale > 0, "color_scale", self.color_scale, "> 0")
        _check(self.depth_scale_m > 0, "depth_scale_m", self.depth_scale_m, "> 0")
        _check(self.speckle_min_px >= 0, "speckle_min_px", self.speckle_min_px, ">= 0")


@dataclass(frozen=True)
class AppearanceParams:
    """Reference-colour check (:mod:`streetcd.detect.appearance`; an addition to the paper, which
    uses the cloud's colours only in the z-buffer): the image against the old cloud's own
    colours, on the inventory classes. ``enabled = False`` is the paper's method."""

    enabled: bool = True
    weight: float = 0.6  # k: the fused change is max(C_p, k · A_p) (tuned, docs/TUNING.md)
    classes: tuple[int, ...] = classes.INVENTORY  # where the reference colours are checked
    # our addition (issue 16): checked as well, against real colours only and only when the
    # cloud tells its road from its ground (:func:`streetcd.detect.roles.road_told`): an
    # added bench or bin stands on the pavement, where eq. 5 sees little (docs/TUNING.md,
    # thirtieth round); the road is left out (cars come and go on it); () for none
    ground_classes: tuple[int, ...] = (GROUND,)
    # our addition (issue 16): checked as well by their hue alone, against real colours only
    # and where the view looks down on them (below the camera's height: hedges, bushes and
    # ground floors, not the crowns and upper floors seen from under them), after a white
    # balance (per-channel gains, no offset, which keeps the hue of dark foliage): a bench or
    # a board in front of a hedge, which eq. 5 weighs by 0.2, or in front of a wall of
    # nearly its brightness; shading and cast shadows change brightness, not hue
    # (docs/TUNING.md, thirty-fifth round); () for none
    hue_classes: tuple[int, ...] = (VEGETATION, BUILDING)
    # gaps narrower than this (px at REFERENCE_WIDTH_PX) inside an inventory object are its
    # footprint too (a railing's see-through gaps); 0 checks the class pixels only
    gap_px: float = 128.0
    # pixels without a surface within this fraction of gap_px of the classes count as them
    # (a railing's surface is mostly holes between its bars); 0: class pixels only
    hole_reach: float = 0.6  # tuned, docs/TUNING.md
    # our addition (issue 16): ... near these roles only (empty: near any checked class),
    # where the cloud's own classes give the roles (inferred roles: near any). Not near
    # poles: a pole near the camera is closed by its own points (surface.point_fill_classes),
    # and a far pole's holes are the sky and the street behind its thin outline, which the
    # check took for the pole (docs/TUNING.md, thirty-second round)
    hole_classes: tuple[int, ...] = (GROUND, SIGN, RAILING, FURNITURE)
    dark_level: float = 24.0  # ε, added to R+G+B (0–765) so dark pixels have no chroma noise
    # our addition (issue 16): ε spread over the channels, ε/3 each, so that a dark colour's
    # chromaticity tends to grey, not to black: the shaded side of a pole that the scanner
    # saw and the lit side a camera on the sidewalk sees differ in brightness, not in chroma
    # (docs/TUNING.md, thirty-sixth round); False: ε added to the sum (black is a colour).
    # The hue_classes' check, without a brightness term, keeps ε on the sum either way
    dark_grey: bool = True
    # our addition (issue 16), a switch left off: a footprint pixel differs from the old
    # colour only as much as the nearer of the transferred and the stored (untransferred)
    # colour. The transfer's offset, fitted to the whole view's means and spreads, can take a
    # dark channel to 0, a hue that is not there (a black railing before a bright street
    # reads as cyan). On: fewer false alarms (validation views flagged without a change 29 →
    # 26 of 106, the pedestrian-left twin 0.93 → 0.55 % of pixels) for less recall (mean
    # kappa 0.653 → 0.648): some removed objects are found only through the colour the
    # transfer made up (docs/TUNING.md, thirty-seventh round); False: the transferred
    # colour alone
    raw_reference: bool = False
    chroma_weight: float = 2.0  # w_c, weight of the L1 chromaticity difference (0–2)
    brightness_weight: float = 0.3  # w_b, weight of the log-brightness difference ...
    brightness_tolerance: float = 0.5  # ... beyond this (ln units: shadows, exposure)
    # our addition (issue 16): the colour transfer's model, "linear" (a gain and an offset
    # per channel, Reinhard's) or "log" (the same on ln(1 + level): exposure and gamma; fewer
    # false alarms on dark objects, as many true ones lost: docs/TUNING.md, twentieth round)
    transfer: str = "linear"
    # our addition (issue 16): a cloud without colours but with intensity gets the intensity
    # check instead (streetcd.detect.intensity: does the inventory still stand out in the
    # image from its surroundings?); False: no check without colours
    intensity: bool = True
    intensity_same_rgb: float = 10.0  # RGB distance to the surroundings' colour: "the same" ...
    intensity_differ_rgb: float = 30.0  # ... up to here, "different" beyond (0-441)
    # the scan must have seen the object differ from its surroundings by this much (mean
    # |ln intensity ratio|) for the check to count in full; 0: no such condition
    intensity_contrast: float = 0.3
    # px at REFERENCE_WIDTH_PX kept clear around the object, beyond the registration
    # tolerance, when taking the surroundings' colour (the object must not be its own)
    intensity_margin_px: float = 12.0

    def __post_init__(self) -> None:
        _codes(self, "appearance.classes", "classes")
        _codes(self, "appearance.ground_classes", "ground_classes")
        _codes(self, "appearance.hue_classes", "hue_classes")
        _codes(self, "appearance.hole_classes", "hole_classes")
        _check(self.weight >= 0, "weight", self.weight, ">= 0")
        _check(
            0 <= self.intensity_same_rgb < self.intensity_differ_rgb,
            "intensity_same_rgb",
            self.intensity_same_rgb,
            ">= 0 and < intensity_differ_rgb",
        )
        _check(self.intensity_contrast >= 0, "intensity_contrast", self.intensity_contrast, ">= 0")
        _check(
            self.intensity_margin_px >= 0, "intensity_margin_px", self.intensity_margin_px, ">= 0"
        )
        _check(self.gap_px >= 0, "gap_px", self.gap_px, ">= 0")
        _check(0 <= self.hole_reach <= 1, "hole_reach", self.hole_reach, "in [0, 1]")
        _check(self.dark_level > 0, "dark_level", self.dark_level, "> 0")
        _check(self.transfer in ("linear", "log"), "transfer", self.transfer, "'linear' or 'log'")
        _check(self.chroma_weight >= 0, "chroma_weight", self.chroma_weight, ">= 0")
        _check(self.brightness_weight >= 0, "brightness_weight", self.brightness_weight, ">= 0")
        _check(
            self.brightness_tolerance >= 0,
            "brightness_tolerance",
            self.brightness_tolerance,
            ">= 0",
        )


@dataclass(frozen=True)
class RefineParams:
    """Pixel outline of the changed regions by colour (:mod:`streetcd.detect.refine`; an addition
    to the paper, whose superpixel cut leaves outlines on superpixel edges).
    ``enabled = False`` keeps the superpixel outlines."""

    enabled: bool = True
    # how far (px at REFERENCE_WIDTH_PX) the outline may move: half a 50 px superpixel cell
    band_px: float = 25.0
    iterations: int = 1  # GrabCut iterations (colour models re-fitted); 1 is the cheapest
    # [ours] roles whose changed pixels are regions apart from the others' (the mask cut one
    # pixel wide where they meet, streetcd.detect.regions.cut_apart): an old car gone or a
    # passer-by beside a new pole is then its own change object, kept out as a transient
    # (issue 17). Empty: the regions are the mask's 8-connected components.
    apart_classes: tuple[int, ...] = (classes.CAR, classes.PEDESTRIAN)

    def __post_init__(self) -> None:
        _check(self.band_px >= 1, "band_px", self.band_px, ">= 1")
        _codes(self, "refine.apart_classes", "apart_classes")
        _check(self.iterations >= 1, "iterations", self.iterations, ">= 1")


@dataclass(frozen=True)
class LocateParams:
    """[ours] Where each changed region stands (:mod:`streetcd.detect.locate`; issue 17):
    the depth, as a fraction of the old surface's behind it, at which the view and its
    neighbours agree best. The change objects place an added thing there (a car parked since
    the scan stands on the road, not on the façade behind it). ``enabled = False``: regions
    are located on the old surface alone."""

    enabled: bool = True
    min_fraction: float = 0.1  # the nearest depth tried, as a fraction of the old surface's
    steps: int = 19  # fractions from min_fraction to 1, evenly (0.05 apart by default)
    min_gain: float = 0.03  # the median colour distance must drop this much below the old surface's
    min_pixels: int = 50  # pixels (at the working scale) seen by a neighbour, at least
    window_px: int = 5  # colours averaged over this square at the working scale
    scale: float = 0.25  # fraction of the image's resolution it runs at ...
    max_work_width_px: int = 512  # ... but never wider than this (its cost at 12 MP)
    max_samples: int = 1500  # on at most this many pixels a region (evenly spread)

    def __post_init__(self) -> None:
        _check(0 < self.min_fraction < 1, "min_fraction", self.min_fraction, "in (0, 1)")
        _check(self.steps >= 3, "steps", self.steps, ">= 3")
        _check(0 <= self.min_gain <= 1, "min_gain", self.min_gain, "in [0, 1]")
        _check(self.min_pixels >= 1, "min_pixels", self.min_pixels, ">= 1")
        _check(self.window_px >= 1, "window_px", self.window_px, ">= 1")
        _check(0 < self.scale <= 1, "scale", self.scale, "in (0, 1]")
        _check(self.max_work_width_px >= 16, "max_work_width_px", self.max_work_width_px, ">= 16")
        _check(
            self.max_samples >= self.min_pixels, "max_samples", self.max_samples, ">= min_pixels"
        )

    def fractions(self) -> tuple[float, ...]:
        """The depth fractions tried, increasing, ending at 1 (the old surface)."""
        step = (1.0 - self.min_fraction) / (self.steps - 1)
        return tuple(self.min_fraction + i * step for i in range(self.steps - 1)) + (1.0,)


SEE_THROUGH = (classes.RAILING,)  # the roles one sees through: railings and fences


@dataclass(frozen=True)
class TextureParams:
    """Texture cue (:mod:`streetcd.detect.texture`; an addition to the paper, whose eq. 5
    compares single pixels): the normalised cross-correlation of the view and each neighbour
    warped through the old surface, over a window. ``enabled = False`` is the paper's method.
    """

    enabled: bool = True  # False: the paper's method (docs/DECISIONS.md, docs/TUNING.md)
    weight: float = 1.0  # the fused change is max(C_p, k · A_p, weight · T_p) (tuned, TUNING.md)
    window_px: int = 11  # NCC window side, at ``scale`` of the image
    min_std: float = 4.0  # grey levels: flatter windows give no evidence
    scale: float = 0.5  # resolution the cue runs at (tolerance to registration error) ...
    # ... but never wider than this: its cost does not grow with the camera's resolution
    max_work_width_px: int = 1024
    # registration error tolerated (px at REFERENCE_WIDTH_PX): the best NCC over shifts of the
    # warped neighbour up to this much (twice eq. 5's envelope: a window's texture needs it)
    registration_tolerance_px: float = 8.0
    # our addition: the whole warped neighbour is first aligned by the shift (up to this, px at
    # REFERENCE_WIDTH_PX) that correlates best with the view, then the windows search around it:
    # pose error beyond the window's tolerance is mostly one shift per view (0: no alignment)
    max_global_shift_px: float = 32.0
    # where the old surface is of these classes (empty: every class); the street inventory
    # by default, the objects a city's database tracks (on façades and trees the texture of a
    # window does not survive the registration error of synthetic streets: docs/TUNING.md)
    classes: tuple[int, ...] = classes.INVENTORY
    # our addition (issue 16): a neighbour gives no evidence where it sees the old surface
    # foreshortened against the view by a factor below this (cos of its viewing angle over
    # the view's, or the inverse): a window's texture does not match across a plane seen
    # edge-on from one side. 0.5, set once: a window seen at half its width (0: every
    # neighbour everywhere; docs/TUNING.md, sixteenth round)
    min_foreshortening: float = 0.5
    # our addition (issue 16): the view and each warped neighbour low-passed with a Gaussian
    # of this σ (px at the working size) before the windows are compared: a texture finer
    # than the whole-pixel search (brick) decorrelates under sub-pixel misregistration
    # (docs/TUNING.md, twentieth round); 0 = none
    blur_px: float = 0.0
    # our addition (issue 16): the footprint of these roles (objects one sees through: a
    # railing's bars and the wall behind them) is also tested under two hypotheses of the old
    # scene, one opaque plane at the object's depth and what is behind it: a hedge or a board
    # where a railing stood is explained by neither (streetcd.detect.seethrough; on since
    # 2026-11-29, empty: off; docs/TUNING.md, eighteenth round)
    see_through_classes: tuple[int, ...] = SEE_THROUGH
    # ... both images low-passed first with a Gaussian of this many metres at the object's
    # depth (σ = blur_m · f / z px): a railing's bars (10-12 cm apart) are a grating that no
    # single depth lines up with the wall behind; its period / 3, set once
    see_through_blur_m: float = 0.04
    # our addition (issue 16): ... and at least this σ (px at the working size) where the old
    # cloud has colours: the colour check reads the same footprint there and sees a hedge
    # where a railing stood by its colour, so the test can give up the detail in which a far
    # railing's bars, finer than two working pixels, look like change under pose error;
    # 0 (the default): the metric blur alone. 1.5 was measured and left off: development
    # +0.003, validation -0.0004 (docs/TUNING.md, thirty-third round)
    see_through_colour_blur_px: float = 0.0
    # our addition (issue 16): pixels whose old surface is nearer than this (m), railings
    # left out, take per neighbour the better of two alignments, the background's shift and
    # the near layer's own (up to near_shift_px at REFERENCE_WIDTH_PX): a pose's translation
    # error moves near objects more than the background behind them (f · δ / z); 0: the
    # background's alone (docs/TUNING.md, thirty-second round)
    near_layer_m: float = 12.0
    near_shift_px: float = 96.0

    def __post_init__(self) -> None:
        _codes(self, "texture.classes", "classes")
        _codes(self, "texture.see_through_classes", "see_through_classes")
        _check(self.weight >= 0, "texture.weight", self.weight, ">= 0")
        _check(
            0 <= self.min_foreshortening <= 1,
            "texture.min_foreshortening",
            self.min_foreshortening,
            "in [0, 1]",
        )
        _check(self.window_px >= 3, "texture.window_px", self.window_px, ">= 3")
        _check(self.min_std >= 0, "texture.min_std", self.min_std, ">= 0")
        _check(self.blur_px >= 0, "texture.blur_px", self.blur_px, ">= 0")
        _check(self.near_layer_m >= 0, "texture.near_layer_m", self.near_layer_m, ">= 0")
        _check(self.near_shift_px >= 0, "texture.near_shift_px", self.near_shift_px, ">= 0")
        _check(
            self.see_through_blur_m >= 0,
            "texture.see_through_blur_m",
            self.see_through_blur_m,
            ">= 0",
        )
        _check(
            self.see_through_colour_blur_px >= 0,
            "texture.see_through_colour_blur_px",
            self.see_through_colour_blur_px,
            ">= 0",
        )
        _check(0 < self.scale <= 1, "texture.scale", self.scale, "in (0, 1]")
        _check(
            self.max_work_width_px >= 64,
            "texture.max_work_width_px",
            self.max_work_width_px,
            ">= 64",
        )
        _check(
            self.registration_tolerance_px >= 0,
            "texture.registration_tolerance_px",
            self.registration_tolerance_px,
            ">= 0",
        )
        _check(
            self.max_global_shift_px >= 0,
            "texture.max_global_shift_px",
            self.max_global_shift_px,
            ">= 0",
        )


INFER_MODES = ("auto", "always", "off")  # ClassMap.infer
# The version of the roles inferred from the geometry (streetcd.detect.infer_roles and when
# streetcd.detect.roles infers), in the results hash unless infer is off: 2 (2026-11-29)
# reads small parts off the ground as foliage and infers for mostly unclassified clouds; 3
# (2026-11-29, seventeenth round) gives a railing its foot back from the ground.
INFER_RULES = 3
# The version of the see-through test's code (streetcd.detect.seethrough), in the results hash
# while it is on: 2 (2026-11-29, nineteenth round) low-passes the images at the texture cue's
# working size, not at a size of their own (results a little different: docs/TUNING.md).
SEE_THROUGH_VERSION = 2
# The version of the nearer-depth test's code (streetcd.detect.sweep), in the results hash while
# it is on: 2 (2026-11-30, thirty-fourth round) gives no evidence unless the view has
# neighbours on both sides (the last view of a walk flagged 5 % of an unchanged street).
NEARER_VERSION = 2


@dataclass(frozen=True)
class ClassMap:
    """[ours] The cloud's class codes (0-255) for each role the method needs
    (:data:`streetcd.classes.ROLES`): a city's scanner, its LAS version (formats 0-5 store
    codes up to 31 only) and its own conventions decide them. A role may have several codes;
    a code in no role counts as unclassified. The default is the ASPRS LAS 1.4 codes where the
    standard has the role (ground 2, low/medium/high vegetation 3-5, building 6, road 11) and
    streetcd's user codes 64-68 for the street inventory it does not name."""

    ground: tuple[int, ...] = (classes.GROUND,)
    road: tuple[int, ...] = (classes.ROAD,)
    vegetation: tuple[int, ...] = (3, 4, classes.VEGETATION)
    building: tuple[int, ...] = (classes.BUILDING,)
    pole: tuple[int, ...] = (classes.POLE,)
    sign: tuple[int, ...] = (classes.SIGN,)
    railing: tuple[int, ...] = (classes.RAILING,)
    furniture: tuple[int, ...] = (classes.FURNITURE,)
    vehicle: tuple[int, ...] = (classes.CAR,)
    # our addition: roles from the geometry (streetcd.detect.infer_roles) for the points in no
    # role: "auto" when under 1 % of the cloud has a useful role (an unclassified cloud loses
    # the ground's low weight and the inventory cues), "always" whatever the share, "off" never
    infer: str = "auto"

    def __post_init__(self) -> None:
        if self.infer is False:  # YAML 1.1 reads an unquoted off as false
            object.__setattr__(self, "infer", "off")
        _check(self.infer in INFER_MODES, "classes.infer", self.infer, f"one of {INFER_MODES}")
        owner: dict[int, str] = {}
        for role in classes.ROLES:
            for code in getattr(self, role):
                where = f"classes.{role}"
                _check(isinstance(code, int) and 0 <= code <= 255, where, code, "codes 0-255")
                _check(code not in owner, where, code, f"in one role only (also {owner.get(code)})")
                owner[code] = role

    def table(self) -> tuple[int, ...]:
        """256 entries: the streetcd code (:data:`streetcd.classes.ROLES`) of each cloud code,
        :data:`streetcd.classes.UNCLASSIFIED` for codes in no role."""
        out = [classes.UNCLASSIFIED] * 256
        for role, code in classes.ROLES.items():
            for user_code in getattr(self, role):
                out[user_code] = code
        return tuple(out)


@dataclass(frozen=True)
class DetectParams:
    """Everything one view's detection needs."""

    zbuffer: ZBufferParams = field(default_factory=ZBufferParams)
    surface: SurfaceParams = field(default_factory=SurfaceParams)
    correlate: CorrelateParams = field(default_factory=CorrelateParams)
    graphcut: GraphCutParams = field(default_factory=GraphCutParams)
    appearance: AppearanceParams = field(default_factory=AppearanceParams)
    refine: RefineParams = field(default_factory=RefineParams)
    texture: TextureParams = field(default_factory=TextureParams)
    locate: LocateParams = field(default_factory=LocateParams)  # [ours] issue 17
    classes: ClassMap = field(default_factory=ClassMap)  # [ours] the cloud's codes → roles
    max_range_m: float = 60.0  # points farther than this from the camera are ignored

    def __post_init__(self) -> None:
        _check(
            math.isfinite(self.max_range_m) and self.max_range_m > 0,
            "max_range_m",
            self.max_range_m,
            "a positive number",
        )


@dataclass(frozen=True)
class SegmentParams:
    """How views are cut into street segments and paired with neighbours (ours: the paper
    describes one view). How many neighbours is the detector's ``correlate.n_neighbours``.

    length_m : the side of the fixed grid cells in the CRS that segments are (DESIGN:
        50–100 m; :mod:`streetcd.run.segments`): the same street keeps its segment ids
        every night.
    max_gap_m : no longer used (segments were cut at gaps of the trajectory; a grid cell
        needs no cut); kept so that configs that set it stay valid.
    neighbour_radius_m, max_candidates : the candidate neighbours of a view are the
        ``max_candidates`` nearest centres within this radius (ranked then by overlap).
    bbox_margin_m : the segment box is the trajectory's box grown by this much, so that it
        covers the street the cameras see and not just the line they drove along.
    roads : a city's road network (GeoPackage, GeoJSON: street centre lines in the CRS of
        the poses; ours): a view within ``roads_max_distance_m`` of a line belongs to the
        piece of it ``length_m`` long at its chainage (:mod:`streetcd.geometry.chainage`),
        id ``r<length>-<road id>-C<chainage>``; other views, and every view without a
        network, to the grid cell. ``roads_id_field``: the attribute holding a street's id
        (its FID when empty).
    """

    length_m: float = 100.0
    max_gap_m: float = 30.0
    neighbour_radius_m: float = 30.0
    max_candidates: int = 12
    bbox_margin_m: float = 15.0
    roads: str = ""  # our addition: a road network's file; "": the grid alone
    roads_id_field: str = ""
    roads_max_distance_m: float = 30.0

    def __post_init__(self) -> None:
        for name in ("length_m", "max_gap_m", "neighbour_radius_m", "roads_max_distance_m"):
            value = getattr(self, name)
            _check(math.isfinite(value) and value > 0, f"segments.{name}", value, "> 0")
        _check(self.max_candidates >= 1, "segments.max_candidates", self.max_candidates, ">= 1")
        _check(
            math.isfinite(self.bbox_margin_m) and self.bbox_margin_m >= 0,
            "segments.bbox_margin_m",
            self.bbox_margin_m,
            ">= 0",
        )


@dataclass(frozen=True)
class RunParams:
    """The nightly run (ours: the paper describes one view).

    segments : how views are cut into segments (:class:`SegmentParams`).
    min_changed_fraction : a view is flagged only when more of its pixels than this changed.
    min_region_fraction : ... and when its largest changed region covers at least this share
        of the image (0.2 %: about 4,100 px at 2 MP). Single-view artefacts are small
        scattered regions (docs/TUNING.md, "Which views are flagged").
    region_score_power : a region's size in that rule is its pixels × its score (mean node
        energy, in [0, 1]) to this power: 0 counts pixels alone; 1 lets a small, sure region
        count as much as a larger, doubtful one (ours; docs/DECISIONS.md).
    write_overlays : also write a JPEG of each flagged image with its changes drawn.
    batch_size : views per Dask task. workers : processes of the local Dask cluster (when no
        scheduler is given). Both change speed only, never results.
    max_image_pixels : an image whose header states more pixels fails its view before it is
        decoded (a decompression bomb). max_failed : how many of the night's views may fail
        before the run exits non-zero (and the flow ends Failed): a count (a whole number
        >= 1) or a fraction of the night's views (< 1); 0: any failure fails the night.
        Neither changes a view's result.
    """

    segments: SegmentParams = field(default_factory=SegmentParams)
    min_changed_fraction: float = 0.0
    min_region_fraction: float = 0.002
    # our addition: the rule's region size is pixels × score ** this (0: pixels alone; 1 with
    # min_region_fraction 0.001: a small sure region counts; off: docs/DECISIONS.md)
    region_score_power: float = 0.0
    write_overlays: bool = True
    # 8, not 4: each task carries its segment's crop views, so fewer tasks per segment is
    # less for the flow process to send (a 10,000-view night 2-5 % shorter: docs/BENCHMARKS.md)
    batch_size: int = 8
    workers: int = 2
    max_image_pixels: int = 100_000_000
    max_failed: float = 0.0

    def __post_init__(self) -> None:
        _check(self.batch_size >= 1, "run.batch_size", self.batch_size, ">= 1")
        _check(self.workers >= 1, "run.workers", self.workers, ">= 1")
        _check(self.max_image_pixels >= 1, "run.max_image_pixels", self.max_image_pixels, ">= 1")
        ok = 0.0 <= self.max_failed < 1.0 or float(self.max_failed).is_integer()
        _check(ok, "run.max_failed", self.max_failed, "a fraction in [0, 1) or a whole count")
        for name in ("min_changed_fraction", "min_region_fraction"):
            value = getattr(self, name)
            _check(0.0 <= value < 1.0, f"run.{name}", value, "in [0, 1)")
        power = self.region_score_power
        _check(math.isfinite(power) and power >= 0, "run.region_score_power", power, ">= 0")


@dataclass(frozen=True)
class Config:
    """Everything a user of streetcd may set: ``detect`` (one view) and ``run`` (the night)."""

    detect: DetectParams = field(default_factory=DetectParams)
    run: RunParams = field(default_factory=RunParams)

    def __post_init__(self) -> None:
        n, k = self.detect.correlate.n_neighbours, self.run.segments.max_candidates
        _check(k >= n, "run.segments.max_candidates", k, f">= detect.correlate.n_neighbours = {n}")

    def results_hash(self) -> str:
        """16 hex digits over every setting that changes a view's result or its segment: the
        detector's, the segments' and the flagging rule's, not ``batch_size`` or ``workers``.

        The blob keeps the layout of the hashes that indexes already hold (the neighbour count
        under ``segments``), so an index made before the settings were gathered here is not
        re-detected for identical results.
        """
        r = self.run
        detect = params_to_dict(self.detect)
        if not self.detect.texture.enabled:
            del detect["texture"]  # a cue that is off changes nothing (and older hashes hold)
        else:
            if not self.detect.texture.max_global_shift_px:
                del detect["texture"]["max_global_shift_px"]  # off: older hashes hold
            if not self.detect.texture.min_foreshortening:
                del detect["texture"]["min_foreshortening"]  # off: older hashes hold
            if not self.detect.texture.blur_px:
                del detect["texture"]["blur_px"]  # off: older hashes hold
            if not self.detect.texture.near_layer_m:  # the background's shift alone: older hold
                del detect["texture"]["near_layer_m"]
                del detect["texture"]["near_shift_px"]
            if not self.detect.texture.see_through_classes:  # off: older hashes hold
                del detect["texture"]["see_through_classes"]
                del detect["texture"]["see_through_blur_m"]
                del detect["texture"]["see_through_colour_blur_px"]
            else:  # its low-pass moved to the cue's working size (2026-11-29): redo the views
                detect["texture"]["see_through_version"] = SEE_THROUGH_VERSION
                if not self.detect.texture.see_through_colour_blur_px:  # older hashes hold
                    del detect["texture"]["see_through_colour_blur_px"]
        if self.detect.classes.infer == "off":
            del detect["classes"]["infer"]  # the roles as before it existed: older hashes hold
        else:  # the inference's rules changed the roles of such clouds (2026-11-29): redo them
            detect["classes"]["infer_rules"] = INFER_RULES
        for key, off in (
            ("spacing_edge_min_depth_m", 0.0),
            ("spacing_edge_min_spacing_m", 0.0),
            ("spacing_edge_max_spacing_m", 0.0),
            ("spacing_edge_classes", []),
        ):
            if detect["surface"][key] == off:  # no limit on the widening: older hashes hold
                del detect["surface"][key]
        if self.detect.zbuffer.reach_colour:  # eq. 2's colour term everywhere: older hashes hold
            del detect["zbuffer"]["reach_colour"]
        if not self.detect.surface.spacing_edge_same_role:  # any roles: older hashes hold
            del detect["surface"]["spacing_edge_same_role"]
        if not self.detect.correlate.second_smallest:  # eq. 5's minimum: older hashes hold
            del detect["correlate"]["second_smallest"]
            del detect["correlate"]["second_smallest_gate"]  # it gates nothing then
        elif not self.detect.correlate.second_smallest_gate:  # no gate: older hashes hold
            del detect["correlate"]["second_smallest_gate"]
        if not self.detect.correlate.align_shift_px:  # the poses as given: older hashes hold
            del detect["correlate"]["align_shift_px"]
            del detect["correlate"]["align_min_gain"]
        if not self.detect.correlate.registration_floor_px:  # scaled alone: older hashes hold
            del detect["correlate"]["registration_floor_px"]
        correlate = self.detect.correlate
        if not correlate.silhouette_edge_threshold or not correlate.silhouette_margin_m:
            del detect["correlate"]["silhouette_edge_threshold"]  # the reach alone: older hold
        if self.detect.correlate.nearer_weight == 0.0:  # no nearer-depth test: older hashes hold
            for key in [k for k in detect["correlate"] if k.startswith("nearer")]:
                del detect["correlate"][key]
        else:  # neighbours on both sides asked for since 2026-11-30: redo the views
            detect["correlate"]["nearer_version"] = NEARER_VERSION
        if not self.detect.graphcut.energy_of_mean:  # the mean of eq. 7: older hashes hold
            del detect["graphcut"]["energy_of_mean"]
        if not self.detect.refine.apart_classes:  # the mask's components: older hashes hold
            del detect["refine"]["apart_classes"]
        if not self.detect.locate.enabled:  # regions on the old surface alone: older hashes hold
            del detect["locate"]
        if self.detect.appearance.transfer == "linear":  # Reinhard's: older hashes hold
            del detect["appearance"]["transfer"]
        if not self.detect.appearance.ground_classes:  # the inventory alone: older hashes hold
            del detect["appearance"]["ground_classes"]
        if not self.detect.appearance.hue_classes:  # no hue check: older hashes hold
            del detect["appearance"]["hue_classes"]
        if not self.detect.appearance.dark_grey:  # dark tends to black: older hashes hold
            del detect["appearance"]["dark_grey"]
        if not self.detect.appearance.raw_reference:  # transferred alone: older hashes hold
            del detect["appearance"]["raw_reference"]
        if not self.detect.appearance.hole_classes:  # holes near any class: older hashes hold
            del detect["appearance"]["hole_classes"]
        if not self.detect.appearance.intensity:  # no intensity check: older hashes hold
            for key in [k for k in detect["appearance"] if k.startswith("intensity")]:
                del detect["appearance"][key]
        if not self.detect.surface.point_fill_classes:  # no points' fill: older hashes hold
            for key in [k for k in detect["surface"] if k.startswith("point_fill")]:
                del detect["surface"][key]
        blob = {
            "detect": detect,
            "segments": {
                **dataclasses.asdict(r.segments),
                "n_neighbours": self.detect.correlate.n_neighbours,
            },
            "min_changed_fraction": r.min_changed_fraction,
            "min_region_fraction": r.min_region_fraction,
            "write_overlays": r.write_overlays,
        }
        if not r.segments.roads:  # the grid alone: older hashes hold
            for key in ("roads", "roads_id_field", "roads_max_distance_m"):
                del blob["segments"][key]  # type: ignore[attr-defined]
        if r.region_score_power:  # 0 is the rule before it existed: older hashes hold
            blob["region_score_power"] = r.region_score_power
        return hashlib.sha256(json.dumps(blob, sort_keys=True).encode()).hexdigest()[:16]

    def replace_run(self, **changes: Any) -> Config:
        """This config with ``run`` settings changed (``None`` values are left as they are)."""
        kept = {k: v for k, v in changes.items() if v is not None}
        return dataclasses.replace(self, run=dataclasses.replace(self.run, **kept))


_NESTED = {
    cls.__name__: cls
    for cls in (
        ZBufferParams,
        SurfaceParams,
        CorrelateParams,
        GraphCutParams,
        AppearanceParams,
        RefineParams,
        TextureParams,
        LocateParams,
        ClassMap,
        DetectParams,
        SegmentParams,
        RunParams,
    )
}


def _build(cls: type, values: dict[str, Any], where: str) -> Any:
    if not isinstance(values, dict):
        raise InputError(f"{where}: expected a mapping of parameters, got {values!r}")
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise InputError(
            f"{where}: unknown parameter(s) {', '.join(unknown)} (known: {', '.join(known)})"
        )
    kwargs = {}
    for name, value in values.items():
        sub = known[name].type
        if isinstance(sub, str) and sub in _NESTED and isinstance(value, dict):
            value = _build(_NESTED[sub], value, f"{where}.{name}")
        elif isinstance(value, list):
            value = tuple(value)
        _check_type(value, sub, f"{where}.{name}")
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except InputError as exc:  # a value out of its range: say where it was given
        raise InputError(f"{where}: {exc}") from None


# YAML scalars by the field types the dataclasses declare (bool is an int to Python: refused)
_SCALARS = {
    "float": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "bool": lambda v: isinstance(v, bool),
}


def _check_type(value: Any, annotation: Any, where: str) -> None:
    """InputError naming the field when a scalar setting has the wrong type (``nan`` in YAML
    is the string 'nan'; ``.nan`` is the number)."""
    ok = _SCALARS.get(annotation) if isinstance(annotation, str) else None
    if ok is not None and not ok(value):
        raise InputError(f"{where} = {value!r} must be a {annotation}")


def params_from_dict(values: dict[str, Any], where: str = "detect") -> DetectParams:
    """DetectParams from a nested dict (the YAML's ``detect:`` block); unknown keys are errors."""
    return _build(DetectParams, values or {}, where)


def _plain(x: Any) -> Any:
    if isinstance(x, tuple):
        return [_plain(v) for v in x]
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    return x


def params_to_dict(params: DetectParams) -> dict[str, Any]:
    """Nested plain dict of ``params`` (tuples as lists), the inverse of params_from_dict."""
    return _plain(dataclasses.asdict(params))


def config_from_dict(values: dict[str, Any] | None, where: str = "config") -> Config:
    """Config from the YAML layout ``{detect: {...}, run: {...}}``; both blocks optional,
    unknown keys anywhere are errors naming where they are."""
    values = values or {}
    if not isinstance(values, dict):
        raise InputError(f"{where}: expected the blocks detect: and run:, got {values!r}")
    unknown = sorted(set(values) - {"detect", "run"})
    if unknown:
        raise InputError(f"{where}: unknown block(s) {', '.join(unknown)} (known: detect, run)")
    detect = params_from_dict(values.get("detect") or {}, f"{where}: detect")
    run = _build(RunParams, values.get("run") or {}, f"{where}: run")
    try:
        return Config(detect, run)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def config_to_dict(config: Config) -> dict[str, Any]:
    """Nested plain dict of ``config`` (the YAML layout), the inverse of config_from_dict."""
    return _plain(dataclasses.asdict(config))


def load_config(path: str | Path | None) -> Config:
    """Load a YAML config (``configs/default.yaml`` layout); None → the defaults."""
    if path is None:
        return Config()
    path = Path(path)
    try:
        values = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"config file not found: {path}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise InputError(f"{path}: not valid YAML{where}: {problem}") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    return config_from_dict(values, str(path))
