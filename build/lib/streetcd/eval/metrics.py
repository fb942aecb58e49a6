"""Accuracy of change masks against ground truth, as the paper's §5 defines it (eq. 12).

All masks are ``(H, W)`` arrays in image rows then columns; ``detected`` and ``truth`` are
bool (or 0/255 uint8, anything non-zero is "changed"), ``instances`` is the ground-truth
change-instance id per pixel (``uint16``, 0 = no change), ``dontcare`` marks pixels that are
left out of every count (cars that differ between epochs, pedestrians, foliage).

Definitions (the paper leaves a few details open; these are ours, and the tests pin them):

* **Pixel counts.** ``N`` is the number of *cared-for* pixels (don't-care removed);
  ``NTP``/``NFP``/``NFN``/``NTN`` the usual confusion counts over them; ``PD = NTP + NFP``
  (positives detected), ``PG = NTP + NFN`` (positives in the ground truth), ``ND = N − PD``,
  ``NG = N − PG``.
* **TP = NTP / PG** (the share of the true change that was found) and **FP = NFP / PD** (the
  share of the detection that is wrong), eq. 12; both are NaN when their denominator is 0.
* **Kappa** (eq. 12): ``KC = (p_o − M) / (1 − M)`` with ``p_o = (NTP + NTN) / N`` and
  ``M = (PD·PG + ND·NG) / N²``. When ``M = 1`` both masks are the same constant (all
  unchanged, or all changed), the agreement is perfect and KC is defined as **1.0**; when one
  mask is constant and the other is not, KC = 0 by the formula. NaN only when ``N = 0``.
* **GDR** (good detection rate): a ground-truth change segment (one instance id in one view)
  is *detected* when the detection mask covers at least ``min_cover`` (50 %) of its
  cared-for pixels, whether one detected component covers it or several together. Segments
  with fewer than ``min_truth_px`` cared-for pixels in a view (slivers at the border or behind
  an occluder) are not counted in that view. GDR = detected segments / counted segments.
* **FDR** (false detection rate): detected segments are the 8-connected components of the
  detection mask. A component whose cared-for pixels lie on ground-truth change for less than
  ``false_max_overlap`` (10 %) of them "appears in an area where there is no change" and is a
  false detection; components entirely inside don't-care are not counted.
  FDR = false components / counted components (NaN when there are none).
* **Totals over views** (Table 1 "Total"): pixel counts are pooled (summed) over all views
  and TP, FP, KC computed from the sums; segment counts are pooled the same way.
* **Per object type** (Table 2), scene level: ``NS`` objects of the type in the scene (both
  epochs), ``NGT`` changed ones seen in at least one evaluated view, ``NCDC`` changed ones
  detected (as above) in at least half of the views in which they are counted, ``NFDC`` false
  components whose pixels mostly lie on a reference surface of that type's class (false
  detections have no ground-truth object, so the class under them names the row, like the
  paper's "house segment" column; "no surface" where the old cloud has none).
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from streetcd import classes as class_codes
from streetcd.errors import InputError

_EIGHT = np.ones((3, 3), dtype=bool)


def _ratio(num: float, den: float) -> float:
    return num / den if den else math.nan


@dataclass(frozen=True)
class PixelCounts:
    """Confusion counts over cared-for pixels; add two to pool views (Table 1 "Total")."""

    ntp: int = 0
    nfp: int = 0
    nfn: int = 0
    ntn: int = 0

    def __add__(self, other: PixelCounts) -> PixelCounts:
        return PixelCounts(
            self.ntp + other.ntp, self.nfp + other.nfp, self.nfn + other.nfn, self.ntn + other.ntn
        )

    @property
    def n(self) -> int:
        return self.ntp + self.nfp + self.nfn + self.ntn

    @property
    def pd(self) -> int:
        return self.ntp + self.nfp

    @property
    def pg(self) -> int:
        return self.ntp + self.nfn

    @property
    def tp(self) -> float:
        """NTP / PG, eq. 12 (fraction, NaN without ground-truth change)."""
        return _ratio(self.ntp, self.pg)

    @property
    def fp(self) -> float:
        """NFP / PD, eq. 12 (fraction, NaN without detection)."""
        return _ratio(self.nfp, self.pd)

    @property
    def flagged(self) -> float:
        """PD / N, the fraction of cared-for pixels flagged as changed."""
        return _ratio(self.pd, self.n)

    @property
    def kappa(self) -> float:
        """Cohen's kappa, eq. 12; 1.0 for identical constant masks, NaN when N = 0."""
        n = self.n
        if n == 0:
            return math.nan
        nd, ng = n - self.pd, n - self.pg
        # (p_o − M) / (1 − M) multiplied through by N², in exact integers: pooled counts of
        # many 12 MP views make N² larger than float64 holds exactly.
        chance = self.pd * self.pg + nd * ng  # M · N²
        if chance == n * n:
            return 1.0
        return (n * (self.ntp + self.ntn) - chance) / (n * n - chance)


@dataclass(frozen=True)
class SegmentCounts:
    """Segment-level counts for GDR and FDR; add two to pool views."""

    n_truth: int = 0  # ground-truth change segments counted
    n_good: int = 0  # of those, covered ≥ min_cover by the detection
    n_detected: int = 0  # detected components counted
    n_false: int = 0  # of those, on no change

    def __add__(self, other: SegmentCounts) -> SegmentCounts:
        return SegmentCounts(
            self.n_truth + other.n_truth,
            self.n_good + other.n_good,
            self.n_detected + other.n_detected,
            self.n_false + other.n_false,
        )

    @property
    def gdr(self) -> float:
        return _ratio(self.n_good, self.n_truth)

    @property
    def fdr(self) -> float:
        return _ratio(self.n_false, self.n_detected)


@dataclass(frozen=True)
class FalseDetection:
    """One false detected component: its size in cared-for pixels and the class under it."""

    pixels: int
    dominant_class: int | None


@dataclass(frozen=True)
class ViewScore:
    """Everything the tables need from one view."""

    pixels: PixelCounts
    segments: SegmentCounts
    coverage: dict[int, float] = field(default_factory=dict)  # counted instance id -> covered
    false_detections: tuple[FalseDetection, ...] = ()


def _bool_mask(a: np.ndarray, name: str, shape: tuple[int, ...] | None) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2:
        raise InputError(f"{name} must be a 2-D (H, W) mask, got shape {a.shape}")
    if shape is not None and a.shape != shape:
        raise InputError(f"{name} has shape {a.shape}, expected {shape} like the detection")
    return a.astype(bool, copy=False)


def pixel_counts(
    detected: np.ndarray, truth: np.ndarray, dontcare: np.ndarray | None = None
) -> PixelCounts:
    """Confusion counts of ``detected`` against ``truth`` over pixels not in ``dontcare``.

    detected, truth, dontcare : (H, W) bool or 0/255 uint8.
    """
    det = _bool_mask(detected, "detected", None)
    gt = _bool_mask(truth, "truth", det.shape)
    care = (
        ~_bool_mask(dontcare, "dontcare", det.shape)
        if dontcare is not None
        else np.ones(det.shape, dtype=bool)
    )
    d, g = det & care, gt & care
    ntp = int(np.count_nonzero(d & g))
    pd, pg, n = int(np.count_nonzero(d)), int(np.count_nonzero(g)), int(np.count_nonzero(care))
    return PixelCounts(ntp=ntp, nfp=pd - ntp, nfn=pg - ntp, ntn=n - pd - pg + ntp)


def truth_coverage(
    detected: np.ndarray,
    instances: np.ndarray,
    dontcare: np.ndarray | None = None,
    min_truth_px: int = 50,
) -> dict[int, float]:
    """Fraction of each ground-truth segment's cared-for pixels that the detection covers.

    instances : (H, W) integer, change-instance id per pixel, 0 = none.
    Returns {instance id: covered fraction in [0, 1]} for segments with at least
    ``min_truth_px`` cared-for pixels.
    """
    det = _bool_mask(detected, "detected", None)
    inst = np.asarray(instances)
    if inst.shape != det.shape:
        raise InputError(f"instances has shape {inst.shape}, expected {det.shape}")
    care = (
        ~_bool_mask(dontcare, "dontcare", det.shape)
        if dontcare is not None
        else np.ones(det.shape, dtype=bool)
    )
    ids = inst[care].astype(np.int64)
    hits = det[care]
    total = np.bincount(ids)
    covered = np.bincount(ids[hits], minlength=total.size)
    return {
        int(i): float(covered[i] / total[i])
        for i in np.flatnonzero(total)
        if i != 0 and total[i] >= max(min_truth_px, 1)
    }


def false_components(
    detected: np.ndarray,
    truth: np.ndarray,
    dontcare: np.ndarray | None = None,
    false_max_overlap: float = 0.1,
    class_raster: np.ndarray | None = None,
) -> tuple[int, list[FalseDetection]]:
    """Detected segments (8-connected components) and the false ones among them (§5 FDR).

    Returns (number of counted components, the false ones). ``class_raster`` (H, W) uint8,
    the reference class per pixel, names the class under each false component.
    """
    det = _bool_mask(detected, "detected", None)
    gt = _bool_mask(truth, "truth", det.shape)
    care = (
        ~_bool_mask(dontcare, "dontcare", det.shape)
        if dontcare is not None
        else np.ones(det.shape, dtype=bool)
    )
    labels, n = ndimage.label(det, structure=_EIGHT)
    if n == 0:
        return 0, []
    lab = labels[care]
    size = np.bincount(lab, minlength=n + 1)
    on_truth = np.bincount(lab[gt[care]], minlength=n + 1)
    counted = np.flatnonzero(size[1:]) + 1
    false = [c for c in counted if on_truth[c] < false_max_overlap * size[c]]
    if not false or class_raster is None:
        return len(counted), [FalseDetection(int(size[c]), None) for c in false]
    # most frequent class under each false component: count (label, class) pairs, then keep
    # the largest count per label (ties: the lower class code)
    is_false = np.zeros(n + 1, dtype=bool)
    is_false[false] = True
    sel = is_false[labels] & care
    keys = labels[sel].astype(np.int64) * 256 + np.asarray(class_raster)[sel]
    pairs, counts = np.unique(keys, return_counts=True)
    lab, cls = pairs // 256, pairs % 256
    order = np.lexsort((cls, -counts, lab))
    first = order[np.r_[True, lab[order][1:] != lab[order][:-1]]]
    dominant = dict(zip(lab[first].tolist(), cls[first].tolist(), strict=True))
    return len(counted), [FalseDetection(int(size[c]), int(dominant[c])) for c in false]


def score_view(
    detected: np.ndarray,
    truth: np.ndarray,
    instances: np.ndarray,
    dontcare: np.ndarray | None = None,
    *,
    class_raster: np.ndarray | None = None,
    min_cover: float = 0.5,
    min_truth_px: int = 50,
    false_max_overlap: float = 0.1,
) -> ViewScore:
    """Pixel and segment counts of one view (see the module docstring for the definitions)."""
    if not 0 < min_cover <= 1:
        raise InputError(f"min_cover = {min_cover} must be in (0, 1]")
    pixels = pixel_counts(detected, truth, dontcare)
    cover = truth_coverage(detected, instances, dontcare, min_truth_px)
    n_comp, false = false_components(detected, truth, dontcare, false_max_overlap, class_raster)
    segments = SegmentCounts(
        n_truth=len(cover),
        n_good=sum(c >= min_cover for c in cover.values()),
        n_detected=n_comp,
        n_false=len(false),
    )
    return ViewScore(pixels, segments, cover, tuple(false))


@dataclass(frozen=True)
class Summary:
    """Table 1 row: pooled counts over views and the rates from them."""

    pixels: PixelCounts
    segments: SegmentCounts

    def as_dict(self) -> dict[str, float | None]:
        """gdr, fdr, tp, fp in percent, kappa in [−1, 1]; undefined values as None."""

        def pct(x: float) -> float | None:
            return None if math.isnan(x) else 100.0 * x

        k = self.pixels.kappa
        return {
            "gdr": pct(self.segments.gdr),
            "fdr": pct(self.segments.fdr),
            "tp": pct(self.pixels.tp),
            "fp": pct(self.pixels.fp),
            "kappa": None if math.isnan(k) else k,
            "flagged": pct(self.pixels.flagged),
        }


def summarize(scores: Iterable[ViewScore]) -> Summary:
    """Pool the views' counts (Table 1 "Total")."""
    pixels, segments = PixelCounts(), SegmentCounts()
    for s in scores:
        pixels, segments = pixels + s.pixels, segments + s.segments
    return Summary(pixels, segments)


@dataclass(frozen=True)
class TypeRow:
    """Table 2 row for one object type."""

    ns: int = 0
    ngt: int = 0
    ncdc: int = 0
    nfdc: int = 0


def per_type_table(
    objects: Sequence[Mapping],
    changes: Sequence[Mapping],
    scores: Sequence[ViewScore],
    min_cover: float = 0.5,
) -> dict[str, TypeRow]:
    """Table 2 at scene level from the manifest's ``objects`` and ``changes`` (see module doc).

    objects : [{id, type, class, ...}], changes : [{instance_id, type, ...}].
    ``scores`` come from :func:`score_view` with ``class_raster`` given, for NFDC.
    """
    ns: Counter = Counter()
    class_to_type: dict[int, set[str]] = defaultdict(set)
    for ob in objects:
        ns[str(ob["type"])] += 1
        if ob.get("class") is not None:
            class_to_type[int(ob["class"])].add(str(ob["type"]))
    seen: dict[int, list[float]] = defaultdict(list)
    for s in scores:
        for inst, cov in s.coverage.items():
            seen[inst].append(cov)
    ngt: Counter = Counter()
    ncdc: Counter = Counter()
    for ch in changes:
        covs = seen.get(int(ch["instance_id"]))
        if not covs:
            continue
        t = str(ch["type"])
        ngt[t] += 1
        if 2 * sum(c >= min_cover for c in covs) >= len(covs):
            ncdc[t] += 1
    nfdc: Counter = Counter()
    for s in scores:
        for f in s.false_detections:
            nfdc[_false_row(f.dominant_class, class_to_type)] += 1
    rows = sorted(set(ns) | set(ngt) | set(nfdc))
    return {t: TypeRow(ns[t], ngt[t], ncdc[t], nfdc[t]) for t in rows}


def _false_row(code: int | None, class_to_type: Mapping[int, set[str]]) -> str:
    """Row name for a false detection: the object type of its class when exactly one type
    has that class, else the class name (``building``, ``vegetation``...)."""
    if code is None:
        return "unknown"
    if code == 0:
        return "no surface"  # the reference cloud has no surface under the detection
    types = class_to_type.get(code, set())
    if len(types) == 1:
        return next(iter(types))
    return class_codes.NAMES.get(code, f"class {code}")
