"""Detection and ego-pose metrics for the online evaluation, in NumPy.

Boxes follow ``geometry``: ``[..., 5] = (x_m, y_m, yaw_rad, length_m, width_m)``, all boxes of one
call in the same frame (ego frame in the evaluation).

Detection
- :func:`rotated_iou`: exact IoU of every pair of rotated rectangles (polygon clipping).
- :func:`nms`: greedy non-maximum suppression on that IoU; :func:`merging_nms`, the same with each kept
  box replaced by the score-weighted mean of the boxes it suppresses that overlap it most.
- :func:`match_detections`: greedy score-ordered matching; each ground truth matched at most once.
- :func:`average_precision`: all-point interpolated AP of a PR curve.
- :class:`DetectionAccumulator`: frame-by-frame AP and PR curves per IoU threshold, overall and per
  group of who saw each box (:data:`GROUPS`), with bootstrap intervals over whole drives
  (:func:`bootstrap_interval`), in memory independent of the number of frames.

Ego pose
- :func:`pose_errors`: location, heading and speed errors.
- :class:`PoseErrorAccumulator`: mean and median of each, and mean location error binned by the
  number of steps since the start of a drive (does filtering converge?).

Everything here but :func:`box_groups` runs on the host in float64: evaluation calls these per frame with
small, varying array sizes, where JAX's per-call dispatch (~1 ms) and per-shape compilation (~0.3 s)
would dominate.
"""

import dataclasses
import math
import warnings
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import summary
from e2e_percep_jax.sim import geometry as geo

# Who saw each ground-truth box, for AP by group; every box falls in exactly one (:func:`box_groups`).
GROUPS = (
    "lidar",  # some lidar beam ends on it in this frame
    "camera_only",  # the camera shows some of it, the lidar none
    "remembered",  # neither sensor now, but one of them within the last REMEMBER_FRAMES frames
    "unseen",  # neither sensor for longer than that, or not since the drive began
)
SUBSETS = ("all",) + GROUPS
REMEMBER_FRAMES = 30  # 3 s at 10 Hz


def _as_boxes(boxes):
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != 5:
        raise ValueError(f"expected boxes of shape [N, 5], got {boxes.shape}")
    return boxes


def _roll_up(a):
    """Each vertex's successor around closed polygons stored vertex-major, ``[V, P] -> [V, P]``."""
    return np.concatenate([a[1:], a[:1]])


def _clamp_to_slab(u, v, half):
    """Maps closed polygons onto the slab ``|u| <= half``: ``u, v [V, P]``, ``half [P]`` -> ``[3V, P]``.

    Each point moves to ``(clip(u, -half, half), v)``. Every edge's image is a polyline bending where
    the edge crosses ``u = -half`` or ``u = +half``, so each edge emits its start and both crossing
    points (crossings outside the edge clamp to its ends: harmless duplicates). The map only moves
    points outside the slab, so the winding number about any point inside is unchanged and the
    signed area of the result is that of the polygon's part inside the slab: clipping by two
    parallel half-planes at once, with fixed sizes and no vertex bookkeeping.
    """
    du, dv = _roll_up(u) - u, _roll_up(v) - v
    parallel = du == 0.0  # edge along the slab: no crossing
    safe_du = np.where(parallel, 1.0, du)
    t_lo, t_hi = (-half - u) / safe_du, (half - u) / safe_du
    t1 = np.where(parallel, 0.0, np.clip(np.minimum(t_lo, t_hi), 0.0, 1.0))
    t2 = np.where(parallel, 0.0, np.clip(np.maximum(t_lo, t_hi), 0.0, 1.0))
    new_u = np.clip(np.stack([u, u + t1 * du, u + t2 * du], axis=1), -half, half)  # [V, 3, P]
    new_v = np.stack([v, v + t1 * dv, v + t2 * dv], axis=1)
    return new_u.reshape(-1, u.shape[1]), new_v.reshape(-1, u.shape[1])


def _clipped_area(quad, half_lw):
    """Area ``[P]`` of convex counter-clockwise quadrilaterals ``quad [P, 4, 2]`` clipped to the
    axis-aligned rectangles ``|x| <= half_lw[:, 0], |y| <= half_lw[:, 1]``: two slab clips, then
    the shoelace formula."""
    x, y = quad[..., 0].T, quad[..., 1].T  # vertex-major [V, P]: contiguous rows
    x, y = _clamp_to_slab(x, y, half_lw[:, 0])
    y, x = _clamp_to_slab(y, x, half_lw[:, 1])
    return 0.5 * np.sum(x * _roll_up(y) - y * _roll_up(x), axis=0)


def rotated_iou(boxes_a, boxes_b):
    """Exact intersection-over-union ``[N, M]`` of rotated boxes ``boxes_a [N, 5]`` and ``boxes_b [M, 5]``.

    Each box of b is expressed in the frame of each box of a, where a is an axis-aligned rectangle,
    and clipped to it (see :func:`_clamp_to_slab`); the area is exact up to float64 rounding.
    Pairs whose circumscribed circles do not meet are skipped (IoU 0). Boxes of zero area give
    IoU 0. Results lie in [0, 1].
    """
    a, b = _as_boxes(boxes_a), _as_boxes(boxes_b)
    iou = np.zeros((len(a), len(b)))
    radius_a = 0.5 * np.hypot(a[:, 3], a[:, 4])
    radius_b = 0.5 * np.hypot(b[:, 3], b[:, 4])
    centre_dist = np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=-1)
    ia, ib = np.nonzero(centre_dist <= radius_a[:, None] + radius_b[None, :])
    if ia.size == 0:
        return iou
    a, b = a[ia], b[ib]
    # b in a's frame, its yaw unwrapped (geometry.box_to_ego wraps it: the same corners, rounded differently)
    b_in_a = np.concatenate([geo.town_to_ego(b[:, :2], a[:, :2], a[:, 2]), (b[:, 2] - a[:, 2])[:, None], b[:, 3:5]], 1)
    quad = geo.box_corners(b_in_a)
    area_a, area_b = a[:, 3] * a[:, 4], b[:, 3] * b[:, 4]
    # Rounding can push a touching pair's area a hair below 0, or an identical pair's above the box area.
    inter = np.clip(_clipped_area(quad, 0.5 * a[:, 3:5]), 0.0, np.minimum(area_a, area_b))
    union = area_a + area_b - inter
    iou[ia, ib] = np.where(union > 0.0, inter / np.where(union > 0.0, union, 1.0), 0.0)
    return iou


def _greedy(boxes, scores, iou_threshold):
    """Greedy rotated NMS's working: (order int64 [M], the boxes by rank; IoU [M, M] between ranks; a
    (rank, taken bool [M]) per kept box, highest score first, ``taken`` marking the ranks it suppresses that no
    higher-scored kept box had, itself included)."""
    boxes = _as_boxes(boxes)
    order = np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")
    # One IoU matrix (one vectorised call), then the greedy pass over it: per-row IoU calls cost
    # ~0.4 ms each in NumPy overhead, which dominated the evaluation's host time.
    iou = rotated_iou(boxes[order], boxes[order])  # [M, M], by rank
    suppressed = np.zeros(len(order), dtype=bool)
    clusters = []
    for rank in range(len(order)):
        if not suppressed[rank]:
            taken = ~suppressed & (iou[rank] > iou_threshold)
            taken[rank] = True
            clusters.append((rank, taken))
            suppressed |= taken
    return order, iou, clusters


def nms(boxes, scores, iou_threshold):
    """Greedy rotated non-maximum suppression.

    Args:
      boxes: ``[M, 5]``. scores: ``[M]``. iou_threshold: a box is dropped when its IoU with an
        already kept, higher-scored box exceeds this (strictly).
    Returns:
      int64 ``[kept]`` indices into ``boxes`` of the kept boxes, highest score first (ties: lower index).
    """
    order, _, clusters = _greedy(boxes, scores, iou_threshold)
    return np.asarray([order[rank] for rank, _ in clusters], dtype=np.int64)


def merging_nms(boxes, scores, iou_threshold, merge_iou):
    """Greedy rotated NMS (:func:`nms`) whose kept boxes become the score-weighted mean of themselves and the
    boxes they suppress that overlap them by more than ``merge_iou`` (>= ``iou_threshold``): centre, length
    and width averaged, the heading averaged as a rectangle's (doubled angles, so that yaw and yaw + pi are
    one), then turned to lie within 90 degrees of the kept box's. A PIXOR map gives a vehicle a fan of boxes
    from its pixels; suppressing at a low IoU removes the fan's false positives, and the mean keeps what
    its better-fitting members knew. Returns (boxes ``[kept, 5]``, scores ``[kept]``: the kept boxes' own),
    highest score first; ``merge_iou`` 1 gives :func:`nms`'s boxes."""
    boxes, scores = _as_boxes(boxes), np.asarray(scores, dtype=np.float64)
    order, iou, clusters = _greedy(boxes, scores, iou_threshold)
    ranked, ranked_scores = boxes[order], scores[order]
    merged = np.empty((len(clusters), 5))
    for i, (rank, taken) in enumerate(clusters):
        members = taken & (iou[rank] > merge_iou)
        members[rank] = True
        if members.sum() == 1:  # nothing to merge: the kept box exactly
            merged[i] = ranked[rank]
            continue
        member_boxes, weight = ranked[members], np.maximum(ranked_scores[members], 1e-12)
        doubled = np.average(np.stack([np.cos(2 * member_boxes[:, 2]), np.sin(2 * member_boxes[:, 2])]), 1, weight)
        yaw = 0.5 * np.arctan2(doubled[1], doubled[0])
        yaw = np.where(np.cos(yaw - ranked[rank, 2]) < 0, geo.wrap_angle(yaw + np.pi), yaw)
        centre, size = (np.average(member_boxes[:, k], 0, weight) for k in (slice(0, 2), slice(3, 5)))
        merged[i] = np.concatenate([centre, [yaw], size])
    return merged, ranked_scores[[rank for rank, _ in clusters]]


def match_detections(pred_boxes, pred_scores, gt_boxes, iou_thresholds):
    """Greedy matching of one frame's detections to its ground truth, for several IoU thresholds.

    Detections are visited by decreasing score (ties: lower index first); each takes the still
    unmatched ground truth of highest IoU, if that IoU >= the threshold. A ground truth is matched
    at most once.

    Args:
      pred_boxes: ``[M, 5]``. pred_scores: ``[M]``. gt_boxes: ``[G, 5]``, real boxes only (no padding).
      iou_thresholds: ``[T]`` thresholds in (0, 1].
    Returns:
      int64 ``[T, M]``: the matched ground-truth index of each detection, -1 if unmatched.
    """
    thresholds = np.asarray(iou_thresholds, dtype=np.float64)
    if np.any((thresholds <= 0.0) | (thresholds > 1.0)):
        raise ValueError(f"IoU thresholds must lie in (0, 1], got {thresholds}")
    iou = rotated_iou(pred_boxes, gt_boxes)  # [M, G]
    pred_scores = np.asarray(pred_scores, dtype=np.float64)
    num_thr, (num_pred, num_gt) = len(thresholds), iou.shape
    if pred_scores.shape != (num_pred,):
        raise ValueError(f"expected {num_pred} scores, got shape {pred_scores.shape}")
    matched = np.full((num_thr, num_pred), -1, dtype=np.int64)
    if num_gt == 0:
        return matched
    gt_taken = np.zeros((num_thr, num_gt), dtype=bool)
    every_thr = np.arange(num_thr)
    for det in np.argsort(-pred_scores, kind="stable"):
        candidate_iou = np.where(gt_taken, -1.0, iou[det])  # [T, G]
        best = candidate_iou.argmax(axis=1)
        ok = candidate_iou[every_thr, best] >= thresholds
        matched[ok, det] = best[ok]
        gt_taken[every_thr[ok], best[ok]] = True
    return matched


def average_precision(precision, recall):
    """All-point interpolated AP (VOC2010+) of a PR curve ordered by decreasing score threshold.

    Precision is replaced by its running maximum from the right (monotone non-increasing), then the
    area is summed over every recall step, the first one (from recall 0) included. Beyond the last
    recall, precision counts as 0. An empty curve gives 0.
    """
    precision, recall = np.asarray(precision, dtype=np.float64), np.asarray(recall, dtype=np.float64)
    envelope = np.maximum.accumulate(precision[::-1])[::-1]
    return float(np.sum(np.diff(recall, prepend=0.0) * envelope))


@dataclasses.dataclass(frozen=True)
class PRCurve:
    """One PR curve and its AP. Arrays ``[L]``: one point per distinct score level, by decreasing score.

    ap: all-point interpolated AP; nan when ``num_gt == 0``, 0 when there are ground truths but no
      detections. precision, recall: at each score level (recall is nan when ``num_gt == 0``).
    score: the level's score threshold (lower edge of its score bin). num_gt: ground truths counted.
    """

    ap: float
    precision: np.ndarray
    recall: np.ndarray
    score: np.ndarray
    num_gt: int


def box_groups(lidar_visible, camera_visible, frames_since_seen):
    """Each box's group, int32 [...]: an index into :data:`GROUPS`, from who saw it (the frame contract's
    ``boxes_lidar_visible``, ``boxes_camera_visible``, ``boxes_frames_since_seen``). In jax.numpy, the one
    function here that runs on the device: the evaluation's program and its choice of drives call it."""
    recent = jnp.asarray(frames_since_seen) <= REMEMBER_FRAMES
    group = jnp.where(lidar_visible, 0, jnp.where(camera_visible, 1, jnp.where(recent, 2, 3)))
    return group.astype(jnp.int32)


# Points of a box's footprint, as fractions of its length and width: 5 along (under a metre apart for a car) and
# 3 across, pulled in from the edges so that a point on an edge does not read the neighbouring pixel.
_FOOTPRINT = np.stack(np.meshgrid(np.linspace(-0.45, 0.45, 5), np.linspace(-0.45, 0.45, 3), indexing="ij"), -1)


def in_lidar_shadow(boxes, lidar_seen):
    """bool [M]: whether the lidar sees none of each box's footprint (``boxes`` [M, 5], ego frame, metres), read
    at 15 points spread over it in the pixels of ``lidar_seen`` bool [R, R] (``bev_latent.lidar_visibility``
    at one cell a pixel; points outside the view are not seen). A detection the lidar sees in part is one the
    sensor can check; one wholly in the shadow only a memory, or a guess, can report."""
    boxes, lidar_seen = _as_boxes(boxes), np.asarray(lidar_seen, bool)
    r = lidar_seen.shape[0]
    local = _FOOTPRINT.reshape(-1, 2) * boxes[:, None, 3:5]  # [M, P, 2]
    points = boxes[:, None, :2] + geo.rotate(local, boxes[:, None, 2])
    pixel = np.floor(geo.ego_to_bev_px(points, r)).astype(np.int64)
    inside = np.all((pixel >= 0) & (pixel < r), -1)
    pixel = np.clip(pixel, 0, r - 1)
    seen = lidar_seen[pixel[..., 0], pixel[..., 1]] & inside
    return ~np.any(seen, -1)


def _ap_from_counts(counts, num_gt):
    """AP of every subset from outcome counts, vectorised over leading axes.

    counts [..., 1 + G, S]: unmatched, then matched to a box of each group, per score bin, highest scores
    first; num_gt [..., G]. Returns [..., 1 + G]: all boxes, then each group (nan without ground truth).
    Empty bins repeat the previous point of the curve, so the area equals that over the score levels.
    """
    fp, tp_group = counts[..., 0, :], counts[..., 1:, :]
    tp = np.concatenate([tp_group.sum(-2, keepdims=True), tp_group], axis=-2)  # [..., 1 + G, S]
    n = np.concatenate([num_gt.sum(-1, keepdims=True), num_gt], axis=-1).astype(np.float64)  # [..., 1 + G]
    cum_tp, cum_fp = np.cumsum(tp, -1), np.cumsum(fp, -1)[..., None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(cum_tp + cum_fp > 0, cum_tp / (cum_tp + cum_fp), 0.0)
        recall = cum_tp / n[..., None]
    envelope = np.flip(np.maximum.accumulate(np.flip(precision, -1), axis=-1), -1)
    ap = np.sum(np.diff(recall, prepend=0.0, axis=-1) * envelope, -1)
    return np.where(n > 0, ap, np.nan)


def bootstrap_interval(statistic, num_drives: int, num_resamples: int = 1000, seed: int = 0, level: float = 0.95):
    """Percentile bootstrap interval over whole drives: ``num_resamples`` resamples of the ``num_drives``
    drives with replacement, each given to ``statistic`` as multiplicities ``weights`` int [n, D]; returns
    (low, high) arrays of the statistic's shape (NaN resamples, e.g. a group with no box in them, are
    left out). ``statistic(weights) -> [n, ...]``."""
    rng = np.random.default_rng(seed)
    weights = rng.multinomial(num_drives, np.full(num_drives, 1.0 / num_drives), size=num_resamples)
    values = np.asarray(statistic(weights), np.float64)
    tail = 100.0 * (1.0 - level) / 2.0
    with warnings.catch_warnings():  # a statistic NaN in every resample has a NaN interval
        warnings.simplefilter("ignore", RuntimeWarning)
        low, high = np.nanpercentile(values, [tail, 100.0 - tail], axis=0)
    return low, high


class DetectionAccumulator:
    """Frame-by-frame detection AP, over all boxes and per group of who saw each box (:data:`GROUPS`),
    kept per drive so that every AP has a bootstrap interval over whole drives.

    Matching (see :func:`match_detections`) runs once per frame against all valid ground truths.
    The groups then only reinterpret its outcome; for a group:
    - recall is over the ground truths of that group;
    - a detection matched to a ground truth of the group is a true positive;
    - a detection matched to a ground truth of another group is excluded (neither TP nor FP);
    - an unmatched detection is a false positive in every group (it cannot be attributed to one),
      so a group's precision is pessimistic.
    Where the caller says which detections lie in the lidar's shadow, the unmatched ones there are also
    counted apart: ``false_positives="shadow"`` scores against them alone, the precision of what a perceiver
    reports where only a memory (or a guess) can put a vehicle.

    Memory is flat in the number of frames: outcomes are counted per drive and score bin, so scores
    (in [0, 1]) closer than ``1 / score_bins`` count as ties (one point of the PR curve).
    """

    def __init__(self, iou_thresholds=(0.1, 0.3, 0.5, 0.7), score_bins=1000):
        self.iou_thresholds = tuple(float(t) for t in iou_thresholds)
        self.score_bins = int(score_bins)
        # per drive: [threshold, outcome (0 unmatched, 1 + g matched a box of group g), score bin], the
        # ground truths of each group, and [threshold, score bin] of the unmatched detections in the shadow
        self._counts, self._num_gt, self._shadow_fp = {}, {}, {}
        self.num_frames = 0

    def add_frame(self, pred_boxes, pred_scores, gt_boxes, gt_valid, gt_group, drive: int = 0, pred_in_shadow=None):
        """Adds one frame of drive ``drive``.

        Args:
          pred_boxes: ``[M, 5]`` detections (after NMS). pred_scores: ``[M]`` in [0, 1].
          gt_boxes: ``[G, 5]`` the world's ground-truth boxes, same frame as the detections.
          gt_valid: bool ``[G]``, False for padding. gt_group: int ``[G]``, each box's index into
          :data:`GROUPS` (:func:`box_groups`).
          pred_in_shadow: bool ``[M]``, whether each detection's footprint lies wholly where the lidar does not
          see (:func:`in_lidar_shadow`); None: not known, and the shadow's counts stay empty for every drive.
        """
        pred_scores = np.asarray(pred_scores, dtype=np.float64)
        if not np.all((pred_scores >= 0.0) & (pred_scores <= 1.0)):  # also catches nan
            raise ValueError("detection scores must lie in [0, 1]")
        gt_valid = np.asarray(gt_valid, dtype=bool)
        gt_boxes = _as_boxes(gt_boxes)[gt_valid]
        gt_group = np.asarray(gt_group, dtype=np.int64)[gt_valid]
        if np.any((gt_group < 0) | (gt_group >= len(GROUPS))):
            raise ValueError(f"gt_group must index GROUPS {GROUPS}")
        if drive not in self._counts:
            self._counts[drive] = np.zeros((len(self.iou_thresholds), 1 + len(GROUPS), self.score_bins), np.int64)
            self._num_gt[drive] = np.zeros(len(GROUPS), np.int64)
        matched = match_detections(pred_boxes, pred_scores, gt_boxes, self.iou_thresholds)  # [T, M]
        # Index -1 (unmatched) picks the appended entry, which is then overridden by outcome 0.
        outcome = np.where(matched < 0, 0, 1 + np.append(gt_group, 0)[matched])
        score_bin = np.minimum((pred_scores * self.score_bins).astype(np.int64), self.score_bins - 1)
        thr_index = np.broadcast_to(np.arange(len(self.iou_thresholds))[:, None], matched.shape)
        np.add.at(self._counts[drive], (thr_index, outcome, np.broadcast_to(score_bin, matched.shape)), 1)
        self._num_gt[drive] += np.bincount(gt_group, minlength=len(GROUPS))
        if pred_in_shadow is not None:
            shadow_fp = self._shadow_fp.setdefault(drive, np.zeros(self._counts[drive][:, 0].shape, np.int64))
            unmatched = (outcome == 0) & np.asarray(pred_in_shadow, bool)
            np.add.at(shadow_fp, (thr_index[unmatched], np.broadcast_to(score_bin, matched.shape)[unmatched]), 1)
        self.num_frames += 1

    def has_shadow(self) -> bool:
        """Whether every frame said which of its detections lie in the lidar's shadow."""
        return bool(self._counts) and set(self._shadow_fp) == set(self._counts)

    def _stacked(self, false_positives: str = "scene"):
        """Counts [D, T, 1 + G, S] with the highest scores first, and ground truths [D, G], over the drives;
        ``false_positives="shadow"``: the unmatched outcome counts only the detections in the lidar's shadow."""
        if false_positives not in ("scene", "shadow"):
            raise ValueError(f"false_positives={false_positives!r}: expected 'scene' or 'shadow'")
        if false_positives == "shadow" and not self.has_shadow():
            raise ValueError("false_positives='shadow': add_frame was not given pred_in_shadow for every frame")
        if not self._counts:
            shape = (len(self.iou_thresholds), 1 + len(GROUPS), self.score_bins)
            return np.zeros((1,) + shape, np.int64), np.zeros((1, len(GROUPS)), np.int64)
        drives = sorted(self._counts)
        counts = np.stack([self._counts[d] for d in drives])
        if false_positives == "shadow":
            counts[:, :, 0] = np.stack([self._shadow_fp[d] for d in drives])
        return counts[..., ::-1], np.stack([self._num_gt[d] for d in drives])

    def _bin_scores(self):
        """[S]: each score bin's lowest score, highest bin first (the order of :meth:`_stacked`'s counts)."""
        return np.arange(self.score_bins)[::-1] / self.score_bins

    def shadow_share(self, score_threshold: float) -> dict:
        """``{iou_threshold: share}``: of the unmatched detections scoring ``score_threshold`` or more, the share
        in the lidar's shadow (None where there is none): how many of the false positives at an operating
        score are guesses where no sensor sees, and how many errors of seeing."""
        scene, shadow = self._stacked()[0][:, :, 0], self._stacked("shadow")[0][:, :, 0]  # [D, T, S], high first
        above = _at_or_above(self._bin_scores(), score_threshold)
        unmatched, in_shadow = scene[..., above].sum((0, 2)), shadow[..., above].sum((0, 2))
        return {t: float(s / n) if n else None for t, s, n in zip(self.iou_thresholds, in_shadow, unmatched)}

    def num_gt(self) -> dict:
        """Ground-truth boxes counted, over all boxes and per group: ``{subset: int}``."""
        n = self._stacked()[1].sum(0)
        return dict(zip(SUBSETS, [int(n.sum())] + [int(v) for v in n]))

    def num_drives(self) -> dict:
        """Drives holding at least one box, over all boxes and per group: ``{subset: int}``."""
        per_drive = self._stacked()[1]
        return dict(zip(SUBSETS, [int(np.sum(per_drive.sum(1) > 0))] + [int(v) for v in (per_drive > 0).sum(0)]))

    def results(self, false_positives: str = "scene"):
        """PR curves: ``{iou_threshold: {subset: PRCurve}}``, subsets :data:`SUBSETS`; the false positives are
        every unmatched detection of the scene, or (``"shadow"``) those in the lidar's shadow."""
        counts, per_drive_gt = self._stacked(false_positives)
        counts, num_gt = counts.sum(0), per_drive_gt.sum(0)
        n = dict(zip(SUBSETS, [int(num_gt.sum())] + [int(v) for v in num_gt]))
        score = self._bin_scores()
        out = {}
        for thr, c in zip(self.iou_thresholds, counts):  # high scores first
            fp = c[0]
            tp = dict(zip(SUBSETS, [c[1:].sum(0)] + list(c[1:])))
            out[thr] = {}
            for subset in SUBSETS:
                level = (tp[subset] + fp) > 0  # score levels holding a counted detection
                cum_tp, cum_fp = np.cumsum(tp[subset][level]), np.cumsum(fp[level])
                precision = cum_tp / (cum_tp + cum_fp)
                recall = cum_tp / n[subset] if n[subset] else np.full(cum_tp.shape, np.nan)
                ap = average_precision(precision, recall) if n[subset] else float("nan")
                out[thr][subset] = PRCurve(ap, precision, recall, score[level], n[subset])
        return out

    def remembered_ap_as_seen(self) -> dict:
        """``{iou_threshold: AP}``: the remembered group's AP had its boxes been found as the lidar group's are
        (at every score level the lidar group's recall), against every false positive of the scene as in the
        groups' AP. What a memory as good as sight would score beside this perceiver's false positives: the
        remembered AP's ceiling, set by precision, not memory. NaN without boxes in either group."""
        counts, num_gt = self._stacked()
        counts, num_gt = counts.sum(0), num_gt.sum(0)  # [T, 1 + G, S] highest scores first, [G]
        lidar, remembered = GROUPS.index("lidar"), GROUPS.index("remembered")
        out = {}
        for thr, c in zip(self.iou_thresholds, counts):
            if not num_gt[lidar] or not num_gt[remembered]:
                out[thr] = float("nan")
                continue
            recall = np.cumsum(c[1 + lidar]) / num_gt[lidar]
            found, cum_fp = recall * num_gt[remembered], np.cumsum(c[0])
            precision = np.where(found + cum_fp > 0, found / np.maximum(found + cum_fp, 1e-300), 0.0)
            out[thr] = average_precision(precision, recall)
        return out

    def intervals(self, num_resamples: int = 1000, seed: int = 0, level: float = 0.95, false_positives: str = "scene"):
        """Bootstrap intervals of every AP over whole drives (:func:`bootstrap_interval`), the false positives
        as in :meth:`results`: ``{iou_threshold: {subset: (low, high)}}``."""
        counts, num_gt = self._stacked(false_positives)
        flat = counts.reshape(len(counts), -1)

        def ap(weights):
            out = []
            for w in np.array_split(weights, max(1, len(weights) // 50)):  # bounded memory
                resampled = (w @ flat).reshape((len(w),) + counts.shape[1:])
                out.append(_ap_from_counts(resampled, (w @ num_gt)[:, None, :]))
            return np.concatenate(out)  # [n, T, 1 + G]

        low, high = bootstrap_interval(ap, len(counts), num_resamples, seed, level)
        return {
            thr: {s: (float(low[i, j]), float(high[i, j])) for j, s in enumerate(SUBSETS)}
            for i, thr in enumerate(self.iou_thresholds)
        }


def matched_scores(boxes, scores, gt_boxes, gt_valid, iou: float) -> np.ndarray:
    """float64 [N]: for each of a frame's N vehicle boxes ``gt_boxes`` [N, 5] (``gt_valid`` [N]), the score of
    the detection (``boxes`` [M, 5], ``scores`` [M]) matched to it at ``iou`` (:func:`match_detections`), -inf
    where none is (and for padding). The matching visits detections by decreasing score, so the boxes matched
    by a detection scoring at least s are those a matching of only the detections scoring at least s finds:
    one matching answers every operating score."""
    best = np.full(len(gt_valid), -np.inf)
    index = np.nonzero(gt_valid)[0]
    matched = match_detections(boxes, scores, gt_boxes[index], [iou])[0]
    best[index[matched[matched >= 0]]] = np.asarray(scores, np.float64)[matched >= 0]
    return best


FOUND_IOU = 0.1  # a vehicle counts as found at the groups' loosest IoU: where it is, not its box's fit


class MemoryAccumulator:
    """What a perceiver keeps of the vehicles it found, frame by frame, per drive.

    A remembered box's vehicle was seen by a sensor within :data:`REMEMBER_FRAMES` frames, which is not the
    same as found: one beam on a corner counts as seen. Here a vehicle is *found* in a frame when a
    detection at or above ``score_threshold`` is matched to it at IoU ``iou`` (:func:`match_detections`).
    For every remembered box this counts whether its vehicle was found in one of the REMEMBER_FRAMES frames
    before (``found_before``), whether it is found now, and both (``kept``). ``kept / found_before`` is
    memory measured apart from the scene's false positives, which pull a small group's AP down whatever it
    keeps (:class:`DetectionAccumulator`). A vehicle slipping behind another is often lost while a sliver of
    it is still seen, before memory is asked for; so the same is counted from the last frame a sensor saw it
    in view: found then (``found_last_seen``), and found then and now (``kept_last_seen``), which is what
    ``experiments/memory_horizon.py`` follows. The last frame a sensor saw it may be one where the camera alone
    saw a sliver (``last_seen_camera_only``), which a grid gated by the lidar does not update from; so the same
    is counted from the last frame the lidar saw it in the drive (``found_last_lidar``, ``kept_last_lidar``).
    A vehicle not found then may still have had a box under the operating threshold: ``scored_last_lidar``
    counts those matched then by a detection at any score the caller passes (the evaluation's floor,
    ``eval.score_floor``), which tells a decoder that scores a partly seen car low from one that has lost it.
    Each drive's frames must come in order, and its boxes in the same vehicle slots every frame (the frame
    contract's order).
    """

    COUNTS = (
        "remembered",
        "found_before",
        "found_now",
        "kept",
        "found_last_seen",
        "kept_last_seen",
        "last_seen_camera_only",
        "found_last_lidar",
        "kept_last_lidar",
        "scored_last_lidar",
    )
    SHARES = {  # name: (count, of count)
        "share_found_before": ("found_before", "remembered"),
        "share_kept": ("kept", "found_before"),
        "share_found_last_seen": ("found_last_seen", "remembered"),
        "share_kept_last_seen": ("kept_last_seen", "found_last_seen"),
        "share_last_seen_camera_only": ("last_seen_camera_only", "remembered"),
        "share_found_last_lidar": ("found_last_lidar", "remembered"),
        "share_kept_last_lidar": ("kept_last_lidar", "found_last_lidar"),
        "share_scored_last_lidar": ("scored_last_lidar", "remembered"),
    }

    def __init__(self, score_threshold: float, iou: float = FOUND_IOU):
        self.score_threshold, self.iou = float(score_threshold), float(iou)
        # per drive and slot: the frame it was last found; whether it was found the last frame a sensor saw it,
        # and the last frame the lidar saw it (at the threshold, and at any score); whether the camera alone saw
        # it that last frame
        self._last_found, self._found_when_seen, self._found_when_lidar, self._camera_last = {}, {}, {}, {}
        self._scored_when_lidar = {}
        self._counts = {}

    def add_frame(self, pred_boxes, pred_scores, gt_boxes, gt_valid, gt_group, drive: int, frame: int):
        """Frame ``frame`` (from the drive's start) of drive ``drive``: arguments as
        :meth:`DetectionAccumulator.add_frame`'s, the ground truths in their vehicle slots."""
        gt_valid = np.asarray(gt_valid, dtype=bool)
        score = matched_scores(_as_boxes(pred_boxes), pred_scores, _as_boxes(gt_boxes), gt_valid, self.iou)
        found, scored = score >= self.score_threshold, score > -np.inf
        last = self._last_found.setdefault(drive, np.full(len(gt_valid), -(10**9)))
        when_seen, when_lidar, camera_last, scored_when_lidar = (
            store.setdefault(drive, np.zeros(len(gt_valid), bool))
            for store in (self._found_when_seen, self._found_when_lidar, self._camera_last, self._scored_when_lidar)
        )
        counts = self._counts.setdefault(drive, np.zeros(len(self.COUNTS), np.int64))
        group = np.asarray(gt_group)
        remembered = gt_valid & (group == GROUPS.index("remembered"))
        before = remembered & (frame - last <= REMEMBER_FRAMES)
        last_seen, last_lidar = remembered & when_seen, remembered & when_lidar
        counts += [
            r.sum()
            for r in (
                remembered,
                before,
                remembered & found,
                before & found,
                last_seen,
                last_seen & found,
                remembered & camera_last,
                last_lidar,
                last_lidar & found,
                remembered & scored_when_lidar,
            )  # in the order of COUNTS
        ]
        last[found] = frame
        lidar, camera = group == GROUPS.index("lidar"), group == GROUPS.index("camera_only")
        seen = lidar | camera  # out of view: found False
        when_seen[seen], when_lidar[lidar], camera_last[seen] = found[seen], found[lidar], camera[seen]
        scored_when_lidar[lidar] = scored[lidar]

    def results(self, num_resamples: int = 1000, seed: int = 0) -> dict:
        """The counts over all drives and the :data:`SHARES` (``share_kept``: of the vehicles found before, the
        share found now), each with its 95 % bootstrap interval over whole drives."""
        counts = np.stack(list(self._counts.values())) if self._counts else np.zeros((1, len(self.COUNTS)), np.int64)
        total = dict(zip(self.COUNTS, (int(v) for v in counts.sum(0))))
        column = {name: counts[:, i] for i, name in enumerate(self.COUNTS)}
        out = dict(total)
        for name, (a, b) in self.SHARES.items():
            out[name] = total[a] / max(total[b], 1)
            ratio = lambda w, a=a, b=b: (w @ column[a]) / np.maximum(w @ column[b], 1)  # [n] shares of resamples
            low, high = bootstrap_interval(ratio, len(counts), num_resamples, seed)
            out[f"{name}_interval95"] = [float(low), float(high)]
        return out


def hidden_by_the_world(lidar_visible, camera_visible, valid, last_seen: int):
    """The memory horizon's choice of drives: box-frames per drive [D] after frame ``last_seen`` in which a
    vehicle that the lidar saw there is in view and seen by neither sensor (each bool [D, T, N])."""
    hidden = valid[:, last_seen + 1 :] & ~(lidar_visible | camera_visible)[:, last_seen + 1 :]
    return (hidden & lidar_visible[:, last_seen, None]).sum((1, 2))


class Occlusion(NamedTuple):
    """One vehicle hidden from both sensors after the lidar saw it (:func:`occlusions`): its box ``slot``, the
    first ``frame`` it is hidden, the ``hidden`` frames it stays in the remembered group, the score of the
    detection matched to it in the frame before (``score_before``, -inf for none) and in each hidden frame
    (``scores`` float [hidden])."""

    slot: int
    frame: int
    hidden: int
    score_before: float
    scores: np.ndarray


def occlusions(group, valid, score, min_hidden: int) -> list:
    """Every stretch of at least ``min_hidden`` frames in which a vehicle is remembered right after a frame in
    which the lidar saw it, for one drive: ``group`` int [T, N] (indices into :data:`GROUPS`), ``valid`` bool
    [T, N], ``score`` float [T, N] (each box's matched detection score, :func:`matched_scores`; -inf for none),
    boxes in their vehicle slots. Ordered by slot, then frame."""
    remembered = np.asarray(valid, bool) & (np.asarray(group) == GROUPS.index("remembered"))
    lidar = np.asarray(valid, bool) & (np.asarray(group) == GROUPS.index("lidar"))
    events = []
    for slot in range(remembered.shape[1]):
        for frame in np.nonzero(lidar[:-1, slot] & remembered[1:, slot])[0] + 1:
            ends = np.nonzero(~remembered[frame:, slot])[0]
            hidden = int(ends[0]) if len(ends) else remembered.shape[0] - frame
            if hidden >= min_hidden:
                scores = np.asarray(score[frame : frame + hidden, slot], np.float64)
                events.append(Occlusion(slot, int(frame), hidden, float(score[frame - 1, slot]), scores))
    return events


def kept_shares(found: dict, in_view, followed, standing, num_resamples: int = 1000) -> dict:
    """The memory horizon (``experiments/memory_horizon.py``): the shares of followed vehicles found k frames
    after the last frame the filter saw, by each run. found: {run:
    bool [D, K, N]} (frame last seen + k, k = 1..K); in_view: bool [D, K, N]; followed: bool [D, N];
    standing: bool [D, K, N]. Returns {"standing" | "moving" | "all": {"boxes": [K], run: [K],
    f"{run}_interval95": [K, 2]}} (shares in [0, 1]; NaN for a k without a box); intervals resample whole
    drives."""
    counted = in_view & followed[:, None, :]
    result = {}
    for name, subset in (("standing", standing), ("moving", ~standing), ("all", np.ones_like(standing))):
        boxes = (counted & subset).sum(-1)  # [D, K]
        entry = {"boxes": boxes.sum(0).tolist()}
        for run, found_by_run in found.items():
            hits = (counted & subset & found_by_run).sum(-1)

            def share(weights, hits=hits):  # weights [n, D] -> [n, K]
                with np.errstate(invalid="ignore", divide="ignore"):
                    return (weights @ hits) / (weights @ boxes)

            entry[run] = share(np.ones((1, len(boxes))))[0].tolist()
            low, high = bootstrap_interval(share, len(boxes), num_resamples)
            entry[f"{run}_interval95"] = np.stack([low, high], -1).tolist()
        result[name] = entry
    return result


class PoseErrors(NamedTuple):
    """Per-step ego pose errors, each ``[...]``."""

    location_m: np.ndarray  # Euclidean distance on (x, y)
    heading_rad: np.ndarray  # in [0, pi]
    speed_mps: np.ndarray  # absolute


def pose_errors(pred_pose, true_pose):
    """Errors of predicted ego poses ``[..., 5] = (x_m, y_m, cos psi, sin psi, speed_mps)``.

    Each (cos, sin) pair is turned into its angle with atan2, which is the angle of the normalised
    direction (atan2 ignores the vector's length), so an unnormalised prediction is fine.
    """
    pred, true = np.asarray(pred_pose, dtype=np.float64), np.asarray(true_pose, dtype=np.float64)
    heading_diff = geo.pose_yaw(pred) - geo.pose_yaw(true)
    return PoseErrors(
        location_m=np.linalg.norm(pred[..., :2] - true[..., :2], axis=-1),
        heading_rad=np.abs(geo.wrap_angle(heading_diff)),
        speed_mps=np.abs(pred[..., 4] - true[..., 4]),
    )


# Shares of frames reported per error kind: error within each bound (location m, heading rad).
WITHIN = {"location_m": (5.0, 10.0, 50.0), "heading_rad": (0.1,)}


class PoseErrorAccumulator:
    """Mean, median and 90th percentile of the pose errors, the share of frames within the bounds of
    :data:`WITHIN`, and mean location error by steps since the start of a drive.

    Step bins are ``[edge_i, edge_{i+1})``, the last one open-ended. For an exact median every error
    is kept, as float32 in one growing buffer (12 bytes per step: 1.2 MB per 100,000 steps); the
    binned sums take constant memory.
    """

    def __init__(self, step_bin_edges=(0, 10, 30, 100, 300, 1000, 3000, 10000)):
        self.step_bin_edges = np.asarray(step_bin_edges, dtype=np.int64)
        if self.step_bin_edges[0] != 0 or np.any(np.diff(self.step_bin_edges) <= 0):
            raise ValueError("step bin edges must start at 0 and increase")
        self._values = np.zeros((len(PoseErrors._fields), 1024), dtype=np.float32)  # [error kind, step]
        self._size = 0
        self._bin_sum = np.zeros(len(self.step_bin_edges))
        self._bin_count = np.zeros(len(self.step_bin_edges), dtype=np.int64)

    def add(self, errors, steps_since_start):
        """Adds ``errors`` (a :class:`PoseErrors` of ``[...]`` arrays) at ``steps_since_start [...]``.

        ``steps_since_start``: int, 0 at a drive's first frame; broadcast against the errors.
        """
        location = np.asarray(errors.location_m, dtype=np.float64).ravel()
        steps = np.broadcast_to(np.asarray(steps_since_start), np.shape(errors.location_m)).ravel()
        if np.any(steps < 0):
            raise ValueError("steps_since_start must be >= 0")
        end = self._size + location.size
        capacity = self._values.shape[1]
        if end > capacity:  # grow at least twofold: amortised O(1) per step
            self._values = np.pad(self._values, ((0, 0), (0, max(capacity, end - capacity))))
        self._values[:, self._size : end] = [np.ravel(e) for e in errors]
        self._size = end
        bins = np.searchsorted(self.step_bin_edges, steps, side="right") - 1
        np.add.at(self._bin_sum, bins, location)
        np.add.at(self._bin_count, bins, 1)

    def results(self):
        """Summary dict (nan where there is no data).

        ``{"location_m" | "heading_rad" | "speed_mps": {"mean": float, "median": float, "p90": float,
        "within": {bound: share}}, "location_m_by_step": {"bin_edges": [B], "mean": [B], "count": [B]}}``
        (a NaN error, a missing estimate, counts as outside every bound).
        """
        out = {}
        for name, values in zip(PoseErrors._fields, self._values[:, : self._size]):
            some = values.size > 0
            out[name] = {
                "mean": float(np.mean(values, dtype=np.float64)) if some else float("nan"),
                "median": float(np.median(values)) if some else float("nan"),
                "p90": float(np.percentile(values, 90)) if some else float("nan"),
                "within": {
                    f"{bound:g}": float(np.mean(values <= bound)) if some else float("nan")
                    for bound in WITHIN.get(name, ())
                },
            }
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self._bin_sum / self._bin_count
        out["location_m_by_step"] = {
            "bin_edges": self.step_bin_edges.copy(),
            "mean": mean,
            "count": self._bin_count.copy(),
        }
        return out


# ----------------------------------------------------------------------------- summaries for metrics.json


def curve_summary(curve, max_points=200):
    """A PRCurve as JSON: AP, num_gt and the curve subsampled to <= max_points (ends kept)."""
    n = len(curve.precision)
    idx = np.unique(np.linspace(0, n - 1, min(n, max_points)).round().astype(int)) if n else np.zeros(0, int)
    clean = lambda a: [None if not np.isfinite(v) else round(float(v), 5) for v in a[idx]]
    return {
        "ap": None if not np.isfinite(curve.ap) else curve.ap,
        "num_gt": curve.num_gt,
        "precision": clean(curve.precision),
        "recall": clean(curve.recall),
        "score": clean(curve.score),
    }


def _at_or_above(score, threshold):
    """Whether each score passes an operating ``threshold`` (a margin for a bin score rounded just below it)."""
    return score >= threshold - 1e-9


def at_threshold(curve, threshold):
    """(precision, recall) of a PR curve when detections need score >= ``threshold``."""
    above = _at_or_above(curve.score, threshold)
    if not np.any(above):
        return None, 0.0 if curve.num_gt else None
    i = np.nonzero(above)[0][-1]
    recall = curve.recall[i]
    return float(curve.precision[i]), (None if not np.isfinite(recall) else float(recall))


def mean_pose(poses):
    """The constant pose closest on average to ``poses [N, 5]``: mean x, y, speed; circular mean heading."""
    poses = np.asarray(poses, np.float64)
    heading = math.atan2(poses[:, 3].mean(), poses[:, 2].mean())
    return np.array([poses[:, 0].mean(), poses[:, 1].mean(), math.cos(heading), math.sin(heading), poses[:, 4].mean()])


CONVERGED_M = 10.0  # a drive has converged from the first frame after which its location error stays below this


def drive_pose_summary(drives_true, drives_pred) -> dict:
    """Per-drive pose figures from each drive's true and estimated poses ([frames, 5] each, in order):
    ``converged_frame`` (per drive: the first frame from which the location error stays below CONVERGED_M,
    None if it never does) with its median over the drives that converge and their share, and
    ``drift_per_100m``: the location error at the drives' last frames over the distance they drove
    (summed over drives), per 100 m: how fast an odometry from a known start drifts."""
    converged, end_error, distance = [], 0.0, 0.0
    for true, pred in zip(drives_true, drives_pred):
        if not len(true):
            continue
        true, pred = np.asarray(true, np.float64), np.asarray(pred, np.float64)
        error = np.linalg.norm(pred[:, :2] - true[:, :2], axis=-1)
        above = np.nonzero(~(error < CONVERGED_M))[0]  # NaN (no pose) counts as not converged
        converged.append(0 if not len(above) else (None if above[-1] == len(error) - 1 else int(above[-1]) + 1))
        end_error += error[-1]
        distance += np.sum(np.linalg.norm(np.diff(true[:, :2], axis=0), axis=-1))
    done = [c for c in converged if c is not None]
    return {
        "converged_frame": {
            "per_drive": converged,
            "within_m": CONVERGED_M,
            "share": len(done) / max(len(converged), 1),
            "median": float(np.median(done)) if done else None,
        },
        "drift_per_100m": summary.defined(float(100.0 * end_error / distance)) if distance > 0 else None,
    }


# The known-start protocol's error by frames of each drive, [first, last + 1) (None: to the drive's end): the
# early frames show the odometry's own drift, the late ones how far it grows (the tables' Table II)
FRAME_SPANS = {"location_m_frames_100_999": (100, 1000), "location_m_frames_1000_on": (1000, None)}


def drive_pose_intervals(drives_true, drives_pred, cover, step_bin_edges, num_resamples: int = 1000) -> dict:
    """95 % bootstrap intervals over whole drives (:func:`bootstrap_interval`) of the pose figures, from each
    drive's true and estimated poses ([frames, 5] each) and ``cover`` ([frames, 2] per drive: how much of
    the truth's cell lies in the belief's 95 % place and (heading, place) regions; None: no belief). Returns
    ``{name: (low, high)}``: location_m_mean, location_m_p90, heading_rad_mean, location_within_5m,
    location_within_10m, drift_per_100m, coverage_place, coverage_place_heading (NaN without a belief), the
    mean location error over each of :data:`FRAME_SPANS` (NaN where no drive reaches it) and
    location_m_by_step_mean (arrays [B], per bin of ``step_bin_edges``)."""
    errors = [pose_errors(p, t) for t, p in zip(drives_true, drives_pred)]
    loc = [np.asarray(e.location_m, np.float64) for e in errors]
    frames = np.array([len(v) for v in loc], np.float64)
    sums = lambda values: np.array([np.sum(v) for v in values], np.float64)
    # each span's (error sum, frames) per drive
    spans = {
        name: [sums(v[first:last] for v in loc), sums(len(v[first:last]) for v in loc)]
        for name, (first, last) in FRAME_SPANS.items()
    }
    bins = [np.searchsorted(step_bin_edges, np.arange(len(v)), side="right") - 1 for v in loc]
    by_step_sum = np.stack([np.bincount(b, v, len(step_bin_edges)) for b, v in zip(bins, loc)])
    by_step_count = np.stack([np.bincount(b, minlength=len(step_bin_edges)) for b in bins]).astype(np.float64)
    travelled = sums([np.linalg.norm(np.diff(np.asarray(t)[:, :2], axis=0), axis=-1) for t in drives_true])
    end_error = np.array([v[-1] if len(v) else 0.0 for v in loc])
    cover_sum = np.stack([np.sum(c, 0) for c in cover]).astype(np.float64) if cover is not None else None

    def statistic(w):
        with np.errstate(invalid="ignore", divide="ignore"):
            n = w @ frames
            p90 = [np.percentile(np.concatenate([np.repeat(v, k) for v, k in zip(loc, row)]), 90) for row in w]
            out = {
                "location_m_mean": (w @ sums(loc)) / n,
                "location_m_p90": np.array(p90),
                "heading_rad_mean": (w @ sums(e.heading_rad for e in errors)) / n,
                "location_within_5m": (w @ sums(v <= 5.0 for v in loc)) / n,
                "location_within_10m": (w @ sums(v <= 10.0 for v in loc)) / n,
                "drift_per_100m": 100.0 * (w @ end_error) / (w @ travelled),
                "coverage_place": (w @ cover_sum[:, 0]) / n if cover is not None else np.full(len(w), np.nan),
                "coverage_place_heading": (w @ cover_sum[:, 1]) / n if cover is not None else np.full(len(w), np.nan),
                **{name: (w @ total) / (w @ count) for name, (total, count) in spans.items()},
            }
            by_step = (w @ by_step_sum) / (w @ by_step_count)
        return np.concatenate([np.stack(list(out.values()), 1), by_step], 1), list(out)

    names = statistic(np.ones((1, len(loc)), np.int64))[1]
    low, high = bootstrap_interval(lambda w: statistic(w)[0], len(loc), num_resamples)
    k = len(names)
    intervals = {name: (low[i], high[i]) for i, name in enumerate(names)}
    intervals["location_m_by_step_mean"] = (low[k:], high[k:])
    return intervals


def pose_summary(acc: PoseErrorAccumulator) -> dict:
    """The accumulator's results as JSON (non-finite means as None)."""
    res = acc.results()
    by_step = res.pop("location_m_by_step")
    res["location_m_by_step"] = {
        "bin_edges": [int(v) for v in by_step["bin_edges"]],
        "mean": [None if not np.isfinite(v) else float(v) for v in by_step["mean"]],
        "count": [int(v) for v in by_step["count"]],
    }
    return res
