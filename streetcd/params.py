"""Parameters of the detector as frozen dataclasses, defaults from the paper (Table 3 and text).

Pixel-sized parameters are given for the paper's images (16 MP, about 4900 px wide) at
``REFERENCE_WIDTH_PX`` and scaled with the image width by :func:`scale_px`; the paper itself
says the edge threshold "varies according to the image resolution" (Table 3).

Loaded from YAML (``configs/default.yaml``) only at the edges, with :func:`load_params`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from streetcd import classes
from streetcd.errors import InputError

REFERENCE_WIDTH_PX = 4000


def scale_px(value_px: float, width_px: int, minimum: float = 1.0) -> float:
    """A pixel length given at ``REFERENCE_WIDTH_PX`` scaled to an image ``width_px`` wide."""
    return max(minimum, value_px * width_px / REFERENCE_WIDTH_PX)


def _check(cond: bool, name: str, value: Any, rule: str) -> None:
    if not cond:
        raise InputError(f"parameter {name} = {value!r} must be {rule}")


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
    # (see streetcd.zbuffer); 0 keeps the paper's fixed w1
    point_spacing_m: float = 0.12

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


@dataclass(frozen=True)
class SurfaceParams:
    """View-dependent triangulation and rasters, paper §3.3 (first paragraph)."""

    max_depth_jump_m: float = 0.5  # triangles spanning more depth than this are dropped
    max_edge_px: float = 30.0  # at REFERENCE_WIDTH_PX; scaled with the image width

    def __post_init__(self) -> None:
        _check(self.max_depth_jump_m > 0, "max_depth_jump_m", self.max_depth_jump_m, "> 0")
        _check(self.max_edge_px > 0, "max_edge_px", self.max_edge_px, "> 0")


@dataclass(frozen=True)
class CorrelateParams:
    """Neighbour re-projection and raw change (eq. 4–5), paper §3.3."""

    n_neighbours: int = 3  # the paper uses 2–3 overlapping views
    occlusion_tolerance_m: float = 0.3  # a pixel is occluded in q if q sees something closer
    stretch_percentiles: tuple[float, float] = (1.0, 99.0)  # histogram stretching per view
    low_weight_classes: tuple[int, ...] = classes.LOW_WEIGHT  # trees, roads (paper), ground
    low_class_weight: float = 0.2  # "a small weight" for those classes
    # colour tolerance for registration error: p's colour is compared with the range of q's
    # colours within this radius (px at REFERENCE_WIDTH_PX; 0 = the paper's pixel difference)
    registration_tolerance_px: float = 4.0  # tuned, docs/TUNING.md (2 px at 1920 wide)
    # > 0: pixels within f·m/z px of a nearer surface at depth z are also tested at that
    # depth (the unscanned side of near poles, streetcd.silhouette); 0 = the paper's method
    silhouette_margin_m: float = 0.2  # tuned, docs/TUNING.md
    # True: each neighbour's levels are fitted to the view's on the pixels they share
    # (streetcd.correlate.pair_lut); False: each image stretched on its own (the paper)
    pair_gain: bool = True
    # holes in q's surface within this distance (px at REFERENCE_WIDTH_PX) of its surface take
    # the nearest-by minimum depth for the occlusion test (streetcd.correlate.hole_depths:
    # near poles leave holes between their sparse points); 0 = holes hide nothing (the paper)
    occluder_fill_px: float = 120.0

    def __post_init__(self) -> None:
        _check(self.n_neighbours >= 1, "n_neighbours", self.n_neighbours, ">= 1")
        _check(self.occluder_fill_px >= 0, "occluder_fill_px", self.occluder_fill_px, ">= 0")
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
    """Reference-colour check (:mod:`streetcd.appearance`; an addition to the paper, which
    uses the cloud's colours only in the z-buffer): the image against the old cloud's own
    colours, on the inventory classes. ``enabled = False`` is the paper's method."""

    enabled: bool = True
    weight: float = 0.6  # k: the fused change is max(C_p, k · A_p) (tuned, docs/TUNING.md)
    classes: tuple[int, ...] = classes.INVENTORY  # where the reference colours are checked
    # gaps narrower than this (px at REFERENCE_WIDTH_PX) inside an inventory object are its
    # footprint too (a railing's see-through gaps); 0 checks the class pixels only
    gap_px: float = 128.0
    # pixels without a surface within this fraction of gap_px of the classes count as them
    # (a railing's surface is mostly holes between its bars); 0: class pixels only
    hole_reach: float = 0.6  # tuned, docs/TUNING.md
    dark_level: float = 24.0  # ε, added to R+G+B (0–765) so dark pixels have no chroma noise
    chroma_weight: float = 2.0  # w_c, weight of the L1 chromaticity difference (0–2)
    brightness_weight: float = 0.3  # w_b, weight of the log-brightness difference ...
    brightness_tolerance: float = 0.5  # ... beyond this (ln units: shadows, exposure)

    def __post_init__(self) -> None:
        _check(self.weight >= 0, "weight", self.weight, ">= 0")
        _check(self.gap_px >= 0, "gap_px", self.gap_px, ">= 0")
        _check(0 <= self.hole_reach <= 1, "hole_reach", self.hole_reach, "in [0, 1]")
        _check(self.dark_level > 0, "dark_level", self.dark_level, "> 0")
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
    """Pixel outline of the changed regions by colour (:mod:`streetcd.refine`; an addition
    to the paper, whose superpixel cut leaves outlines on superpixel edges).
    ``enabled = False`` keeps the superpixel outlines."""

    enabled: bool = True
    # how far (px at REFERENCE_WIDTH_PX) the outline may move: half a 50 px superpixel cell
    band_px: float = 25.0
    iterations: int = 1  # GrabCut iterations (colour models re-fitted); 1 is the cheapest

    def __post_init__(self) -> None:
        _check(self.band_px >= 1, "band_px", self.band_px, ">= 1")
        _check(self.iterations >= 1, "iterations", self.iterations, ">= 1")


@dataclass(frozen=True)
class DetectParams:
    """Everything one view's detection needs."""

    zbuffer: ZBufferParams = field(default_factory=ZBufferParams)
    surface: SurfaceParams = field(default_factory=SurfaceParams)
    correlate: CorrelateParams = field(default_factory=CorrelateParams)
    graphcut: GraphCutParams = field(default_factory=GraphCutParams)
    appearance: AppearanceParams = field(default_factory=AppearanceParams)
    refine: RefineParams = field(default_factory=RefineParams)
    max_range_m: float = 60.0  # points farther than this from the camera are ignored

    def __post_init__(self) -> None:
        _check(
            math.isfinite(self.max_range_m) and self.max_range_m > 0,
            "max_range_m",
            self.max_range_m,
            "a positive number",
        )


def _build(cls: type, values: dict[str, Any], where: str) -> Any:
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise InputError(
            f"{where}: unknown parameter(s) {', '.join(unknown)} (known: {', '.join(known)})"
        )
    kwargs = {}
    for name, value in values.items():
        sub = known[name].type
        nested = {
            "ZBufferParams": ZBufferParams,
            "SurfaceParams": SurfaceParams,
            "CorrelateParams": CorrelateParams,
            "GraphCutParams": GraphCutParams,
            "AppearanceParams": AppearanceParams,
            "RefineParams": RefineParams,
        }
        if isinstance(sub, str) and sub in nested and isinstance(value, dict):
            value = _build(nested[sub], value, f"{where}.{name}")
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)


def params_from_dict(values: dict[str, Any], where: str = "params") -> DetectParams:
    """DetectParams from a nested dict (the YAML layout); unknown keys are errors."""
    return _build(DetectParams, values or {}, where)


def params_to_dict(params: DetectParams) -> dict[str, Any]:
    """Nested plain dict of ``params`` (tuples as lists), the inverse of params_from_dict."""

    def plain(x: Any) -> Any:
        if isinstance(x, tuple):
            return [plain(v) for v in x]
        if isinstance(x, dict):
            return {k: plain(v) for k, v in x.items()}
        return x

    return plain(dataclasses.asdict(params))


def load_params(path: str | Path | None) -> DetectParams:
    """Load a YAML parameter file (``configs/default.yaml`` layout); None → paper defaults."""
    if path is None:
        return DetectParams()
    import yaml

    path = Path(path)
    try:
        values = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise InputError(f"parameter file not found: {path}") from None
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML: {exc}") from None
    return params_from_dict(values.get("detect", values), str(path))
