"""Detection and pose metrics against brute force, closed forms and hand-computed cases."""

import math

import numpy as np
import pytest

from e2e_percep_jax import metrics
from e2e_percep_jax.sim import geometry as geo

THRESHOLDS = (0.1, 0.3, 0.5, 0.7)


def box(x, y, yaw, length, width):
    return np.array([x, y, yaw, length, width], dtype=np.float64)


# ---------------------------------------------------------------- rotated IoU


def _inside(points, b):
    """Point-in-rotated-rectangle, written here independently of the library."""
    dx, dy = points[..., 0] - b[0], points[..., 1] - b[1]
    c, s = math.cos(b[2]), math.sin(b[2])
    along, across = c * dx + s * dy, -s * dx + c * dy
    return (np.abs(along) <= b[3] / 2) & (np.abs(across) <= b[4] / 2), np.maximum(
        np.abs(along) - b[3] / 2, np.abs(across) - b[4] / 2
    )


def _grid_intersection(a, b, n=400):
    """Intersection area of boxes a, b from an n x n grid of cell centres tiling a, with an error bound.

    The cells tile a exactly, so only cells that b's boundary may cross are uncertain: those whose
    centre lies within half a cell diagonal of it (|max(|u| - l/2, |v| - w/2)| never exceeds the
    distance to a rectangle's boundary).
    """
    cell_l, cell_w = a[3] / n, a[4] / n
    u = (np.arange(n) + 0.5) * cell_l - a[3] / 2
    v = (np.arange(n) + 0.5) * cell_w - a[4] / 2
    uu, vv = np.meshgrid(u, v, indexing="ij")
    c, s = math.cos(a[2]), math.sin(a[2])
    points = np.stack([a[0] + c * uu - s * vv, a[1] + s * uu + c * vv], axis=-1)
    inside_b, boundary_dist = _inside(points, b)
    uncertain = np.abs(boundary_dist) <= 0.5 * math.hypot(cell_l, cell_w)
    cell_area = cell_l * cell_w
    return inside_b.sum() * cell_area, uncertain.sum() * cell_area


def test_rotated_iou_matches_point_grid_on_random_pairs():
    rng = np.random.default_rng(0)
    num = 100
    centres = rng.uniform(-2, 2, (2, num, 2)) + rng.uniform(-50, 50, (1, num, 2))  # pairs near each other
    sizes = rng.uniform([0.5, 0.3], [6.0, 3.0], (2, num, 2))
    yaws = rng.uniform(-np.pi, np.pi, (2, num))
    a = np.concatenate([centres[0], yaws[0, :, None], sizes[0]], axis=1)
    b = np.concatenate([centres[1], yaws[1, :, None], sizes[1]], axis=1)
    iou = metrics.rotated_iou(a, b)
    assert iou.shape == (num, num)
    np.testing.assert_allclose(iou, metrics.rotated_iou(b, a).T, atol=1e-12)  # symmetry
    assert np.all((iou >= 0.0) & (iou <= 1.0))
    overlapping = 0
    for i in range(num):
        inter, bound = _grid_intersection(a[i], b[i])
        area_a, area_b = a[i, 3] * a[i, 4], b[i, 3] * b[i, 4]
        exact_inter = iou[i, i] * (area_a + area_b) / (1.0 + iou[i, i])  # invert IoU = I / (A + B - I)
        assert abs(exact_inter - inter) <= bound + 1e-9, (i, exact_inter, inter, bound)
        overlapping += inter > 0
    assert overlapping > 50  # the test exercises real overlaps, not mostly zeros


OCTAGON = 2 * (math.sqrt(2) - 1)  # unit square ∩ its 45° rotation about the centre: a regular octagon


@pytest.mark.parametrize(
    "a, b, expected",
    [
        (box(0, 0, 0.3, 4, 2), box(0, 0, 0.3, 4, 2), 1.0),  # identical
        (box(312.5, -207.25, 2.9, 4.5, 1.9), box(312.5, -207.25, 2.9, 4.5, 1.9), 1.0),  # identical, far away
        (box(0, 0, 0, 4, 2), box(4, 0, 0, 4, 2), 0.0),  # touching along an edge
        (box(0, 0, 0.7, 4, 2), box(4 * math.cos(0.7), 4 * math.sin(0.7), 0.7, 4, 2), 0.0),  # rotated, touching
        (box(0, 0, 0, 2, 2), box(2, 2, 0, 2, 2), 0.0),  # touching at a corner
        (box(0, 0, 0, 2, 2), box(10, 0, 0.5, 2, 2), 0.0),  # disjoint
        (box(0, 0, 0, 2, 2), box(2.5, 0, math.pi / 4, 2, 2), 0.0),  # disjoint but within circumscribed circles
        (box(1, 1, 0.4, 6, 4), box(1.5, 1.2, 0.4, 2, 1), 2 / 24),  # nested, same yaw
        (box(0, 0, 0, 6, 4), box(0.5, 0.2, 1.0, 2, 1), 2 / 24),  # nested, rotated
        (box(0, 0, 0, 2, 2), box(0, 0, math.pi / 2, 2, 2), 1.0),  # square turned 90°
        (box(0, 0, 0, 4, 2), box(0, 0, math.pi / 2, 4, 2), 4 / 12),  # rectangle turned 90°: a cross
        (box(0, 0, 0, 1, 1), box(0, 0, math.pi / 4, 1, 1), OCTAGON / (2 - OCTAGON)),
        (box(0, 0, 0.5, 4, 2), box(math.cos(0.5), math.sin(0.5), 0.5, 4, 2), 3 / 5),  # collinear edges, shifted
        (box(0, 0, 0, 4, 2), box(0, 0, math.pi, 4, 2), 1.0),  # same footprint, opposite heading
    ],
)
def test_rotated_iou_closed_forms(a, b, expected):
    assert metrics.rotated_iou(a[None], b[None])[0, 0] == pytest.approx(expected, abs=1e-9)
    assert metrics.rotated_iou(b[None], a[None])[0, 0] == pytest.approx(expected, abs=1e-9)


def test_rotated_iou_empty_inputs():
    assert metrics.rotated_iou(np.zeros((0, 5)), np.ones((3, 5))).shape == (0, 3)
    assert metrics.rotated_iou(np.ones((2, 5)), np.zeros((0, 5))).shape == (2, 0)


# ---------------------------------------------------------------- NMS


def test_nms_collapses_duplicates_to_the_best_and_keeps_separate_boxes():
    car_a, car_b = box(0, 0, 0.2, 4.5, 2), box(0, 5, -0.1, 4.5, 2)
    boxes = np.stack(
        [car_a + [0.2, 0, 0, 0, 0], car_b, car_a, car_b + [0, 0.3, 0.05, 0, 0], car_a + [-0.1, 0.1, 0, 0, 0]]
    )
    scores = np.array([0.6, 0.7, 0.9, 0.5, 0.8])
    np.testing.assert_array_equal(metrics.nms(boxes, scores, 0.3), [2, 1])


def test_nms_keeps_all_non_overlapping_boxes_by_score():
    boxes = np.stack([box(10.0 * i, 0, 0.3 * i, 4, 2) for i in range(5)])
    scores = np.array([0.2, 0.9, 0.5, 0.7, 0.1])
    np.testing.assert_array_equal(metrics.nms(boxes, scores, 0.1), [1, 3, 2, 0, 4])
    assert metrics.nms(np.zeros((0, 5)), np.zeros(0), 0.5).shape == (0,)


def test_merging_nms_keeps_nms_order_and_averages_each_kept_box_with_what_it_suppresses():
    """A fan of boxes on car A (yaw 0.1, and the same rectangle at yaw pi - 0.1, i.e. -0.1), a box on A that
    overlaps the top one by less than the merge IoU (suppressed, not averaged) and car B alone: A's kept box
    is the score-weighted mean, by hand, of the fan, its heading the rectangle's mean turned towards its own."""
    top, twin = box(0, 0, 0.1, 4.5, 2), box(0.4, 0.2, math.pi - 0.1, 5.0, 2.2)
    far_off = box(1.5, 0.9, 0.5, 4.5, 2)  # overlaps A by IoU in (0.01, 0.5)
    car_b = box(0, 8, 0.3, 4.5, 2)
    boxes, scores = np.stack([twin, car_b, top, far_off]), np.array([0.6, 0.7, 0.9, 0.8])
    iou = metrics.rotated_iou(boxes, boxes)
    assert iou[2, 0] > 0.5 and 0.01 < iou[2, 3] < 0.5 and iou[1, [0, 2, 3]].max() == 0.0
    merged, merged_scores = metrics.merging_nms(boxes, scores, 0.01, 0.5)
    np.testing.assert_array_equal(merged_scores, [0.9, 0.7])
    w = np.array([0.9, 0.6])
    centre = (w[0] * top[:2] + w[1] * twin[:2]) / w.sum()
    size = (w[0] * top[3:] + w[1] * twin[3:]) / w.sum()
    yaw = 0.5 * math.atan((w[0] - w[1]) / w.sum() * math.tan(0.2))  # of unit vectors at +-0.2 rad, doubled
    np.testing.assert_allclose(merged[0, [0, 1, 3, 4]], [*centre, *size])
    np.testing.assert_allclose(merged[0, 2], yaw)
    np.testing.assert_array_equal(merged[1], car_b)
    # merge IoU 1: nms's own boxes; an empty frame stays empty
    plain, plain_scores = metrics.merging_nms(boxes, scores, 0.3, 1.0)
    kept = metrics.nms(boxes, scores, 0.3)
    np.testing.assert_array_equal(plain, boxes[kept])
    np.testing.assert_array_equal(plain_scores, scores[kept])
    empty, empty_scores = metrics.merging_nms(np.zeros((0, 5)), np.zeros(0), 0.01, 0.2)
    assert empty.shape == (0, 5) and empty_scores.shape == (0,)


# ---------------------------------------------------------------- matching and AP


def test_one_ground_truth_is_matched_at_most_once():
    gt = np.stack([box(0, 0, 0, 4, 2), box(0, 1.5, 0, 4, 2)])  # two cars side by side, overlapping
    # Both detections overlap gt 0 best; the second must fall back to gt 1 (IoU 3.2/12.8), not reuse gt 0.
    det = np.stack([box(0, 0.2, 0, 4, 2), box(0, 0.3, 0, 4, 2)])
    matched = metrics.match_detections(det, np.array([0.9, 0.8]), gt, (0.1, 0.5))
    np.testing.assert_array_equal(matched, [[0, 1], [0, -1]])
    # Two detections on a single ground truth: one TP, one FP.
    acc = metrics.DetectionAccumulator((0.5,))
    acc.add_frame(det, np.array([0.9, 0.8]), gt[:1], np.ones(1, bool), np.zeros(1, bool))
    curve = acc.results()[0.5]["all"]
    np.testing.assert_allclose(curve.precision, [1.0, 0.5])
    np.testing.assert_allclose(curve.recall, [1.0, 1.0])


def test_average_precision_of_a_hand_computed_pr_sequence():
    # Ranked TP, FP, TP, FP, TP against 4 ground truths.
    precision = np.array([1, 1 / 2, 2 / 3, 2 / 4, 3 / 5])
    recall = np.array([1, 1, 2, 2, 3]) / 4
    # Envelope from the right: 1, 2/3, 2/3, 3/5, 3/5; recall steps of 1/4 at ranks 1, 3, 5.
    expected = 0.25 * 1 + 0.25 * (2 / 3) + 0.25 * (3 / 5)
    assert metrics.average_precision(precision, recall) == pytest.approx(expected, abs=1e-12)
    assert metrics.average_precision([], []) == 0.0


def _cars(n):
    return np.stack([box(8.0 * i, 0, 0.1 * i, 4.5, 2) for i in range(n)])


def _frame(acc, det, scores, gt, group=None, valid=None, drive=0):
    k = len(gt)
    acc.add_frame(
        det,
        np.asarray(scores, float),
        gt,
        np.ones(k, bool) if valid is None else valid,
        np.zeros(k, int) if group is None else group,
        drive=drive,
    )


def test_accumulator_pr_curve_and_ap_over_frames():
    acc = metrics.DetectionAccumulator(THRESHOLDS)
    gt = _cars(4)
    miss = box(0, 30, 0, 4.5, 2)
    # The sequence of the previous test, spread over two frames, added in arbitrary score order.
    _frame(acc, np.stack([gt[0], miss]), [0.9, 0.6], gt[:2])
    _frame(acc, np.stack([miss, gt[3], gt[2]]), [0.8, 0.5, 0.7], gt[2:])
    for thr, subsets in acc.results().items():
        curve = subsets["all"]
        assert curve.num_gt == 4
        np.testing.assert_allclose(curve.precision, [1, 1 / 2, 2 / 3, 2 / 4, 3 / 5])
        np.testing.assert_allclose(curve.recall, [0.25, 0.25, 0.5, 0.5, 0.75])
        np.testing.assert_allclose(curve.score, [0.9, 0.8, 0.7, 0.6, 0.5], atol=1e-4)  # bin edges
        # Dropping the first recall step, as the reference did, would give 0.3167.
        assert curve.ap == pytest.approx(0.25 + 0.25 * 2 / 3 + 0.25 * 3 / 5, abs=1e-12)


def test_accumulator_perfect_all_false_empty_and_threshold_dependence():
    gt = _cars(3)
    perfect = metrics.DetectionAccumulator(THRESHOLDS)
    _frame(perfect, gt, [0.9, 0.8, 0.7], gt)
    assert all(s["all"].ap == pytest.approx(1.0) for s in perfect.results().values())

    all_false = metrics.DetectionAccumulator(THRESHOLDS)
    _frame(all_false, gt + [0, 20, 0, 0, 0], [0.9, 0.8, 0.7], gt)
    assert all(s["all"].ap == 0.0 for s in all_false.results().values())

    no_detections = metrics.DetectionAccumulator(THRESHOLDS)
    _frame(no_detections, np.zeros((0, 5)), [], gt)
    assert all(s["all"].ap == 0.0 and s["all"].precision.size == 0 for s in no_detections.results().values())

    no_gt = metrics.DetectionAccumulator(THRESHOLDS)
    _frame(no_gt, gt, [0.9, 0.8, 0.7], np.zeros((0, 5)))
    for s in no_gt.results().values():
        assert math.isnan(s["all"].ap) and s["all"].num_gt == 0
        np.testing.assert_allclose(s["all"].precision, [0, 0, 0])

    # A detection shifted 1.4 m along a 4.5 m x 2 m car: IoU 6.2 / 11.8 = 0.525, a match at IoU <= 0.5 only.
    shifted = metrics.DetectionAccumulator(THRESHOLDS)
    _frame(shifted, gt[:1] + [1.4, 0, 0, 0, 0], [0.9], gt[:1])
    assert [s["all"].ap for s in shifted.results().values()] == pytest.approx([1, 1, 1, 0])


def test_padding_ground_truth_is_ignored():
    gt = _cars(2)
    acc = metrics.DetectionAccumulator((0.5,))
    _frame(acc, gt, [0.9, 0.8], gt, valid=np.array([True, False]))
    curve = acc.results()[0.5]["all"]
    assert curve.num_gt == 1
    np.testing.assert_allclose(curve.precision, [1.0, 0.5])  # the detection on the padded box is an FP


def test_groups_split_as_documented():
    gt = _cars(3)
    lidar, remembered = metrics.GROUPS.index("lidar"), metrics.GROUPS.index("remembered")
    acc = metrics.DetectionAccumulator((0.5,))
    # 0.9 hits lidar gt 0, 0.8 hits nothing, 0.7 hits remembered gt 1; remembered gt 2 is missed.
    group = np.array([lidar, remembered, remembered])
    _frame(acc, np.stack([gt[0], box(0, 30, 0, 4, 2), gt[1]]), [0.9, 0.8, 0.7], gt, group=group)
    res = acc.results()[0.5]
    assert acc.num_gt() == {"all": 3, "lidar": 1, "camera_only": 0, "remembered": 2, "unseen": 0}
    assert (res["all"].num_gt, res["lidar"].num_gt, res["remembered"].num_gt) == (3, 1, 2)
    np.testing.assert_allclose(res["all"].precision, [1, 1 / 2, 2 / 3])
    np.testing.assert_allclose(res["all"].recall, [1 / 3, 1 / 3, 2 / 3])
    assert res["all"].ap == pytest.approx(1 / 3 + 1 / 3 * 2 / 3)
    # Lidar: the remembered match (0.7) is excluded; the unmatched detection is an FP.
    np.testing.assert_allclose(res["lidar"].precision, [1, 1 / 2])
    np.testing.assert_allclose(res["lidar"].recall, [1, 1])
    np.testing.assert_allclose(res["lidar"].score, [0.9, 0.8], atol=1e-4)
    assert res["lidar"].ap == pytest.approx(1.0)
    # Remembered: the lidar match (0.9) is excluded; the unmatched detection is an FP here too.
    np.testing.assert_allclose(res["remembered"].precision, [0, 1 / 2])
    np.testing.assert_allclose(res["remembered"].recall, [0, 1 / 2])
    assert res["remembered"].ap == pytest.approx(0.25)
    assert math.isnan(res["camera_only"].ap) and math.isnan(res["unseen"].ap)


def test_the_remembered_ap_as_seen_is_the_groups_ap_when_memory_matches_sight():
    """Two closed forms of the ceiling: with as many remembered boxes as lidar ones and none of them found,
    it is the lidar group's own AP (the same precision at every recall); with half as many remembered boxes,
    one found at the score of each pair of lidar boxes (so the same recall at every score), it is the
    remembered group's actual AP."""
    rng = np.random.default_rng(5)
    lidar, remembered = metrics.GROUPS.index("lidar"), metrics.GROUPS.index("remembered")
    hidden_missed, hidden_found = metrics.DetectionAccumulator(THRESHOLDS), metrics.DetectionAccumulator(THRESHOLDS)
    ghosts = np.stack([box(30, -12 + 6 * i, 0, 4.5, 2) for i in range(3)])  # they match nothing
    for drive in range(4):
        gt = np.stack([box(-20 + 8 * i, 8 * (i % 2), 0, 4.5, 2) for i in range(6)])
        offset = rng.normal(0, 0.3, (6, 5)) * [1, 1, 0.05, 0, 0]
        pair_scores, ghost_scores = rng.uniform(0.05, 1, 2), rng.uniform(0.05, 1, 3)
        # 2 lidar boxes found, 2 remembered missed
        group = np.array([lidar, lidar, remembered, remembered, lidar, lidar])
        det = np.concatenate([gt[:2] + offset[:2], ghosts])
        _frame(hidden_missed, det, np.concatenate([pair_scores, ghost_scores]), gt[:4], group=group[:4], drive=drive)
        # 4 lidar boxes found in two pairs of equal score, 2 remembered ones at those scores, with the same errors
        group = np.array([lidar, lidar, remembered, lidar, lidar, remembered])
        det = np.concatenate([gt + offset[[0, 0, 0, 1, 1, 1]], ghosts])
        scores = np.concatenate([pair_scores[[0, 0, 0, 1, 1, 1]], ghost_scores])
        _frame(hidden_found, det, scores, gt, group=group, drive=drive)
    assert hidden_found.num_gt()["lidar"] == 2 * hidden_found.num_gt()["remembered"]
    for thr in THRESHOLDS:
        assert hidden_missed.remembered_ap_as_seen()[thr] == pytest.approx(hidden_missed.results()[thr]["lidar"].ap)
        assert hidden_found.remembered_ap_as_seen()[thr] == pytest.approx(hidden_found.results()[thr]["remembered"].ap)
    assert hidden_missed.results()[0.5]["remembered"].ap == 0.0 < hidden_missed.remembered_ap_as_seen()[0.5]
    assert math.isnan(metrics.DetectionAccumulator(THRESHOLDS).remembered_ap_as_seen()[0.5])


def test_the_shadow_ap_counts_only_the_false_positives_the_lidar_cannot_see():
    """The groups' frame above with a second unmatched detection: in sight at 0.8, in the shadow at 0.75. Over
    the scene the remembered match at 0.7 comes third (AP 1/2 x 1/3); against the shadow's false positives
    alone, second (AP 1/2 x 1/2). Without the shadow's flags that figure is refused."""
    gt = _cars(3)
    lidar, remembered = metrics.GROUPS.index("lidar"), metrics.GROUPS.index("remembered")
    group = np.array([lidar, remembered, remembered])
    det = np.stack([gt[0], box(0, 30, 0, 4, 2), box(0, -30, 0, 4, 2), gt[1]])
    acc = metrics.DetectionAccumulator((0.5,))
    acc.add_frame(det, [0.9, 0.8, 0.75, 0.7], gt, np.ones(3, bool), group, pred_in_shadow=[False, False, True, True])
    assert acc.results()[0.5]["remembered"].ap == pytest.approx(1 / 6)
    shadow = acc.results(false_positives="shadow")[0.5]["remembered"]
    np.testing.assert_allclose(shadow.precision, [0, 1 / 2])
    assert shadow.ap == pytest.approx(1 / 4)
    low, high = acc.intervals(50, false_positives="shadow")[0.5]["remembered"]
    assert low == high == pytest.approx(1 / 4)  # one drive: every resample is that drive
    # of the false positives at 0.8 and 0.75, one in the shadow; at 0.78 only the one in sight; none at 0.85
    assert acc.shadow_share(0.5) == {0.5: 0.5} and acc.shadow_share(0.78) == {0.5: 0.0}
    assert acc.shadow_share(0.85) == {0.5: None}
    unknown = metrics.DetectionAccumulator((0.5,))
    _frame(unknown, det, [0.9, 0.8, 0.75, 0.7], gt, group=group)
    assert not unknown.has_shadow()
    with pytest.raises(ValueError, match="pred_in_shadow"):
        unknown.results(false_positives="shadow")


@pytest.mark.parametrize("thr", THRESHOLDS)
def test_the_shadow_ap_is_the_ap_with_the_unmatched_detections_in_sight_left_out(thr):
    """Brute force on random frames: dropping a detection that matched nothing changes no other match, so the
    shadow's curves equal those of the scene with the unmatched detections in sight removed; with fewer
    false positives no group's AP falls; and the shadow's share of the false positives above a score is their
    count."""
    rng = np.random.default_rng(11)
    flagged, pruned = metrics.DetectionAccumulator((thr,)), metrics.DetectionAccumulator((thr,))
    unmatched_above, in_shadow_above = 0, 0  # counted here: the unmatched detections scoring 0.5 or more
    for drive in range(6):
        for _ in range(5):
            gt = np.stack([box(*rng.uniform(-20, 20, 2), rng.uniform(-3, 3), 4.5, 2) for _ in range(6)])
            group = rng.integers(0, len(metrics.GROUPS), 6)
            det = np.concatenate(
                [gt[:4] + rng.normal(0, 0.5, (4, 5)) * [1, 1, 0.1, 0, 0], gt[4:] * 0 + [0, 0, 0, 4, 2]]
            )
            det[4:, :2] = rng.uniform(-20, 20, (2, 2))
            scores, in_shadow = rng.uniform(0, 1, 6), rng.random(6) < 0.5
            flagged.add_frame(det, scores, gt, np.ones(6, bool), group, drive=drive, pred_in_shadow=in_shadow)
            unmatched = metrics.match_detections(det, scores, gt, (thr,))[0] < 0
            keep = ~(unmatched & ~in_shadow)
            unmatched_above += np.sum(unmatched & (scores >= 0.5))
            in_shadow_above += np.sum(unmatched & in_shadow & (scores >= 0.5))
            pruned.add_frame(det[keep], scores[keep], gt, np.ones(6, bool), group, drive=drive)
    shadow, scene, reference = (
        flagged.results(false_positives="shadow")[thr],
        flagged.results()[thr],
        pruned.results()[thr],
    )
    for subset in metrics.SUBSETS:
        np.testing.assert_allclose(shadow[subset].ap, reference[subset].ap, equal_nan=True)
        assert not shadow[subset].ap < scene[subset].ap  # NaN for an empty group
    assert flagged.intervals(200, false_positives="shadow") == pruned.intervals(200)
    assert unmatched_above > in_shadow_above > 0
    assert flagged.shadow_share(0.5) == {thr: pytest.approx(in_shadow_above / unmatched_above)}


def test_a_box_is_in_the_shadow_where_the_lidar_sees_none_of_its_footprint():
    """A box shrunk to a point reads the pixel it lies on (round trip through the BEV view's pixel centres); a
    car over unseen pixels is in the shadow until one pixel under its footprint, its front end's, is seen; one
    turned by 90 degrees covers the pixels across instead."""
    r = 16  # 2 m pixels
    seen = np.random.default_rng(2).random((r, r)) < 0.5
    centres = np.asarray(geo.bev_pixel_centres(r, np)).reshape(-1, 2)
    points = np.concatenate([centres, np.tile([0.3, 0.01, 0.01], (r * r, 1))], axis=1)
    np.testing.assert_array_equal(metrics.in_lidar_shadow(points, seen), ~seen.reshape(-1))
    car = np.array([[1.0, 1.0, 0.0, 4.4, 2.2]])  # x 1 m ahead, spans pixels 8-10 down, 7 across
    hidden = np.zeros((r, r), bool)
    assert metrics.in_lidar_shadow(car, hidden).all()
    row, col = np.floor(geo.ego_to_bev_px(np.array([1.0 + 2.0, 1.0]), r)).astype(int)  # under its front end
    corner = hidden.copy()
    corner[row, col] = True
    assert not metrics.in_lidar_shadow(car, corner).any()
    turned = car + [0, 0, np.pi / 2, 0, 0]  # now spans across, not down: the front's pixel is not under it
    assert metrics.in_lidar_shadow(turned, corner).all()


def test_box_groups_partition_by_who_saw_the_box():
    never = np.iinfo(np.int32).max
    lidar = np.array([True, True, False, False, False, False, False])
    camera = np.array([True, False, True, False, False, False, False])
    since = np.array([0, 0, 0, 1, 30, 31, never])
    names = [metrics.GROUPS[g] for g in metrics.box_groups(lidar, camera, since)]
    assert names == ["lidar", "lidar", "camera_only", "remembered", "remembered", "unseen", "unseen"]


def test_vectorised_ap_equals_the_curves_ap():
    """The bootstrap's AP over score bins (empty bins included) against the PR curve's over its levels."""
    rng = np.random.default_rng(3)
    acc = metrics.DetectionAccumulator(THRESHOLDS)
    for drive in range(6):
        gt = np.stack([box(rng.uniform(-10, 15), rng.uniform(-12, 12), rng.uniform(-1, 1), 4.5, 2) for _ in range(5)])
        det = gt + rng.normal(0, 0.6, gt.shape) * [1, 1, 0.1, 0, 0]
        det = np.concatenate([det, det[:2] + [6, 0, 0, 0, 0]])
        _frame(acc, det, rng.uniform(0, 1, len(det)), gt, group=rng.integers(0, 4, 5), drive=drive)
    counts, num_gt = acc._stacked()
    ap = metrics._ap_from_counts(counts.sum(0), num_gt.sum(0)[None])
    for i, (thr, curves) in enumerate(acc.results().items()):
        np.testing.assert_allclose(ap[i], [curves[s].ap for s in metrics.SUBSETS], rtol=1e-12)
    # Every drive resampled once: the interval collapses onto the point estimate.
    low, high = metrics.bootstrap_interval(lambda w: np.ones((len(w), 6)) @ np.arange(6.0)[:, None], 6)
    assert low == high == 15.0


def test_bootstrap_interval_of_two_drives_is_exact():
    """Two drives, values a and b: a resample's mean is a, (a + b) / 2 or b with probability 1/4, 1/2, 1/4,
    so the 2.5 % and 97.5 % points are a and b exactly."""
    a, b = 2.0, 5.0
    mean = lambda w: (w @ np.array([a, b])) / w.sum(1)
    low, high = metrics.bootstrap_interval(mean, 2, num_resamples=4000)
    assert (low, high) == (a, b)


def test_pose_intervals_of_two_drives_span_the_drives_own_figures():
    """Two drives: a resample holds drive a twice, both, or drive b twice, so each figure's 2.5 % and 97.5 %
    points are the two drives' own figures, whatever the figure's weighting (frames, metres driven); drive b
    stops before frame 1,000, so the late span's interval is drive a's alone."""
    drives = []
    for frames, offset_m, slope in ((1500, 1.0, 0.002), (800, 3.0, 0.01)):
        true = np.zeros((frames, 5))
        true[:, 0], true[:, 2] = 0.5 * np.arange(frames), 1.0  # driving along x at 5 m/s (0.1 s frames)
        pred = true.copy()
        pred[:, 1] = offset_m + slope * np.arange(frames)  # the error grows along the drive
        drives.append((true, pred))
    got = metrics.drive_pose_intervals(*zip(*drives), None, np.array([0, 100, 1000]), num_resamples=4000)
    own = []
    for true, pred in drives:
        error_m = np.linalg.norm(pred[:, :2] - true[:, :2], axis=-1)
        own.append(
            {
                "location_m_mean": error_m.mean(),
                "drift_per_100m": 100 * error_m[-1] / (0.5 * (len(error_m) - 1)),
                "location_m_frames_100_999": error_m[100:1000].mean(),
            }
        )
    for name in own[0]:
        np.testing.assert_allclose(got[name], sorted(drive[name] for drive in own), rtol=1e-9, err_msg=name)
    late = np.linalg.norm(drives[0][1][1000:, :2] - drives[0][0][1000:, :2], axis=-1).mean()
    np.testing.assert_allclose(got["location_m_frames_1000_on"], [late, late], rtol=1e-9)


def test_bootstrap_interval_of_a_mean_against_the_normal_closed_form():
    """Over D drives with one value each, the bootstrap distribution of the mean has variance s^2 / D (s^2
    the values' plug-in variance) and is nearly normal for D = 400: the 95 % interval is the mean
    +- 1.96 s / sqrt(D) to within the resampling noise of the percentiles (~2 % at 20,000 resamples)."""
    values = np.random.default_rng(0).exponential(2.0, 400)
    half = 1.96 * values.std() / np.sqrt(len(values))
    low, high = metrics.bootstrap_interval(lambda w: w @ values / len(values), len(values), num_resamples=20_000)
    assert (high - low) / 2 == pytest.approx(half, rel=0.04)
    # the exponential's skew moves the interval right of the symmetric one, by much less than its width
    assert (low + high) / 2 == pytest.approx(values.mean(), abs=0.1 * half)


def test_detection_intervals_hold_the_estimate_and_shrink_with_more_drives():
    rng = np.random.default_rng(1)

    def accumulate(num_drives):
        acc = metrics.DetectionAccumulator((0.5,))
        for drive in range(num_drives):
            gt = _cars(3)
            hit = rng.uniform(size=3) < 0.6  # each car found with probability 0.6
            det = np.concatenate([gt[hit], [box(0, 30, 0, 4, 2)]])
            _frame(acc, det, rng.uniform(0.1, 1, len(det)), gt, drive=drive)
        return acc

    widths = []
    for d in (20, 320):
        acc = accumulate(d)
        low, high = acc.intervals()[0.5]["all"]
        assert low <= acc.results()[0.5]["all"].ap <= high
        widths.append(high - low)
    assert widths[1] < 0.5 * widths[0]  # 1 / sqrt(16) = 0.25 in theory


def test_scores_must_be_probabilities():
    acc = metrics.DetectionAccumulator()
    with pytest.raises(ValueError):
        _frame(acc, _cars(1), [1.5], _cars(1))
    with pytest.raises(ValueError):
        _frame(acc, _cars(1), [np.nan], _cars(1))


# ---------------------------------------------------------------- pose


def pose(x, y, psi, speed, scale=1.0):
    return np.array([x, y, scale * math.cos(psi), scale * math.sin(psi), speed])


def test_pose_errors_closed_forms():
    err = metrics.pose_errors(pose(3, 4, 0.0, 5.0), pose(0, 0, 0.0, 7.5))
    assert err.location_m == pytest.approx(5.0)
    assert err.speed_mps == pytest.approx(2.5)
    assert err.heading_rad == pytest.approx(0.0)
    # Across the ±pi seam, and with an unnormalised predicted direction.
    err = metrics.pose_errors(pose(0, 0, math.pi - 0.1, 0, scale=3.0), pose(0, 0, -math.pi + 0.1, 0))
    assert err.heading_rad == pytest.approx(0.2, abs=1e-12)
    opposite = metrics.pose_errors(pose(0, 0, 0.5, 0), pose(0, 0, 0.5 + math.pi, 0))
    assert opposite.heading_rad == pytest.approx(math.pi)
    batch = metrics.pose_errors(np.zeros((2, 3, 5)) + pose(1, 0, 0, 0), np.zeros((2, 3, 5)))
    assert batch.location_m.shape == (2, 3) and np.allclose(batch.location_m, 1.0)


def test_pose_accumulator_mean_median_and_step_bins():
    acc = metrics.PoseErrorAccumulator(step_bin_edges=(0, 2, 4))
    location = np.array([4.0, 3.0, 2.0, 1.0, 1.0, 0.0])
    zeros = np.zeros(6)
    # Two chunks of one drive (steps 0..5), the second with a [1, 2] batch shape.
    acc.add(metrics.PoseErrors(location[:4], zeros[:4], zeros[:4] + 1), np.arange(4))
    acc.add(metrics.PoseErrors(location[None, 4:], zeros[None, 4:], zeros[None, 4:] + 3), np.arange(4, 6)[None])
    res = acc.results()
    # p90 by NumPy's linear interpolation: sorted [0, 1, 1, 2, 3, 4], position 4.5 -> 3.5.
    assert res["location_m"] == {
        "mean": pytest.approx(11 / 6),
        "median": pytest.approx(1.5),
        "p90": pytest.approx(3.5),
        "within": {"5": 1.0, "10": 1.0, "50": 1.0},
    }
    assert res["heading_rad"]["within"] == {"0.1": 1.0} and res["speed_mps"]["within"] == {}
    assert res["speed_mps"]["mean"] == pytest.approx(10 / 6)
    assert res["speed_mps"]["median"] == pytest.approx(1.0)
    np.testing.assert_allclose(res["location_m_by_step"]["mean"], [3.5, 1.5, 0.5])
    np.testing.assert_array_equal(res["location_m_by_step"]["count"], [2, 2, 2])
    assert math.isnan(metrics.PoseErrorAccumulator().results()["heading_rad"]["mean"])


def test_pose_accumulator_grows_past_its_initial_buffer():
    acc = metrics.PoseErrorAccumulator()
    rng = np.random.default_rng(0)
    chunks = [rng.uniform(0, 10, n) for n in (700, 1, 3000, 5)]
    for i, chunk in enumerate(chunks):
        acc.add(metrics.PoseErrors(chunk, chunk / 10, chunk * 2), i)
    every = np.concatenate(chunks)
    res = acc.results()
    assert res["location_m"]["median"] == pytest.approx(np.median(every), rel=1e-6)
    assert res["location_m"]["p90"] == pytest.approx(np.percentile(every, 90), rel=1e-6)
    assert res["location_m"]["within"]["5"] == pytest.approx(np.mean(every <= 5.0))
    assert res["heading_rad"]["within"]["0.1"] == pytest.approx(np.mean(every / 10 <= 0.1))
    assert res["heading_rad"]["mean"] == pytest.approx(np.mean(every) / 10, rel=1e-6)
    np.testing.assert_array_equal(res["location_m_by_step"]["count"][:2], [len(every), 0])


def test_memory_counts_a_remembered_box_as_found_before_only_if_its_vehicle_was_detected_at_the_threshold():
    """35 frames, four cars in fixed slots. A: detected (0.9) while the lidar sees it (frames 0-9), then
    remembered and not detected (10-34). B: seen and detected (0.8) throughout. C: seen 0-9 but detected
    only at 0.3, under the threshold, then remembered (10-19), then gone. D: detected (0.9) while seen
    (0-9), then remembered and still detected (0.6) for 5 frames (10-14), then gone. Of the 40 remembered
    boxes, A's 25 and D's 5 were found before (the last find while seen, frame 9, lies within 30 frames of
    all of them), C's 10 were not; D's 5 are kept: 5 of 30. At any score, C's last frame in the lidar's view
    matched too: all 40 were scored then. One drive: each interval is its own value."""
    lidar, remembered = metrics.GROUPS.index("lidar"), metrics.GROUPS.index("remembered")
    acc = metrics.MemoryAccumulator(score_threshold=0.5)
    for k in range(35):
        a, b = [5.0 + 0.2 * k, 3.5, 0.0, 4.5, 1.9], [10.0, -4.0, 0.0, 4.5, 1.9]
        c, d = [-6.0, 6.0, 0.0, 4.5, 1.9], [-6.0, -8.0, 0.0, 4.5, 1.9]
        valid = np.array([True, True, k < 20, k < 15])
        hidden = lidar if k < 10 else remembered
        detected = ([a, c] if k < 10 else []) + [b] + ([d] if k < 15 else [])
        scores = ([0.9, 0.3] if k < 10 else []) + [0.8] + ([0.9 if k < 10 else 0.6] if k < 15 else [])
        group = np.array([hidden, lidar, hidden, hidden])
        acc.add_frame(np.reshape(detected, (-1, 5)), scores, np.array([a, b, c, d]), valid, group, drive=0, frame=k)
    out = acc.results(num_resamples=20)
    assert [out[k] for k in acc.COUNTS] == [40, 30, 5, 5, 30, 5, 0, 30, 5, 40]  # A, D found when last seen, C not
    assert out["share_found_before"] == 30 / 40 and out["share_kept"] == 5 / 30
    assert out["share_found_last_seen"] == 30 / 40 and out["share_kept_last_seen"] == 5 / 30
    np.testing.assert_allclose(out["share_kept_interval95"], [5 / 30, 5 / 30])


def test_memory_counts_from_the_last_frame_a_sensor_saw_the_vehicle():
    """A car slipping behind another: seen and detected (frames 0-4), seen but lost (5-9: a sliver in view),
    remembered (10-19) and detected again at 10 and 11. All 10 remembered boxes were found before and 2 are
    kept, but none was found the last frame it was seen, so none counts as kept from there. A second car is
    seen by the camera alone and detected (0-9), then remembered and detected (10-19): found when last seen,
    kept in all its 10 frames. One drive: each interval is its own value."""
    lidar, camera, remembered = (metrics.GROUPS.index(g) for g in ("lidar", "camera_only", "remembered"))
    acc = metrics.MemoryAccumulator(score_threshold=0.5)
    a, b = [8.0, 3.0, 0.0, 4.5, 1.9], [-6.0, -6.0, 0.0, 4.5, 1.9]
    for k in range(20):
        detected = ([a] if k < 5 or k in (10, 11) else []) + [b]
        group = np.array([lidar if k < 10 else remembered, camera if k < 10 else remembered])
        acc.add_frame(np.reshape(detected, (-1, 5)), [0.9] * len(detected), np.array([a, b]), [True, True], group, 0, k)
    out = acc.results(num_resamples=20)
    assert [out[k] for k in acc.COUNTS] == [20, 20, 12, 12, 10, 10, 10, 0, 0, 0]  # the lidar never saw the second
    assert out["share_kept"] == 12 / 20 and out["share_found_last_seen"] == 10 / 20
    assert out["share_kept_last_seen"] == 1.0


def test_memory_counts_from_the_last_frame_the_lidar_saw_the_vehicle():
    """Two cars leave the lidar's view for the camera's, then are hidden. A: seen by the lidar and detected
    (frames 0-4), seen by the camera alone and lost (5-9), remembered (10-19) and detected again at 10-12: found
    the last frame the lidar saw it, not the last frame a sensor did. C: seen by the lidar but detected only at
    0-3 (at frame 4, the lidar's last, only under the threshold), then seen by the camera alone and detected
    (5-9), remembered and detected throughout (10-19): found the last frame a sensor saw it, not the last frame
    the lidar did, yet scored then. The camera alone saw both last."""
    lidar, camera, remembered = (metrics.GROUPS.index(g) for g in ("lidar", "camera_only", "remembered"))
    acc = metrics.MemoryAccumulator(score_threshold=0.5)
    a, c = [8.0, 3.0, 0.0, 4.5, 1.9], [-6.0, -6.0, 0.0, 4.5, 1.9]
    for k in range(20):
        detected = ([a] if k < 5 or k in (10, 11, 12) else []) + [c]
        scores = [0.9] * (len(detected) - 1) + [0.3 if k == 4 else 0.9]
        hidden = lidar if k < 5 else camera if k < 10 else remembered
        acc.add_frame(
            np.reshape(detected, (-1, 5)),
            scores,
            np.array([a, c]),
            [True, True],
            np.array([hidden, hidden]),
            0,
            k,
        )
    out = acc.results(num_resamples=20)
    assert [out[k] for k in acc.COUNTS] == [20, 20, 13, 13, 10, 10, 20, 10, 3, 20]
    assert out["share_last_seen_camera_only"] == 1.0 and out["share_found_last_lidar"] == 10 / 20
    assert out["share_kept_last_lidar"] == 3 / 10 and out["share_scored_last_lidar"] == 1.0


def test_memory_forgets_a_find_older_than_the_remembered_window():
    """A car found at frame 0 only, then remembered from frame 1 (its group as the caller gives it): found
    before through frame 30, not from frame 31 (REMEMBER_FRAMES = 30); a second drive is counted apart."""
    remembered = metrics.GROUPS.index("remembered")
    acc = metrics.MemoryAccumulator(score_threshold=0.5)
    car = np.array([[8.0, 0.0, 0.0, 4.5, 1.9]])
    for drive in (0, 1):
        for k in range(40):
            shown = k == 0 and drive == 0
            acc.add_frame(
                car if shown else np.zeros((0, 5)), [0.9] if shown else [], car, [True], [remembered], drive, k
            )
    out = acc.results(num_resamples=20)
    assert [out[k] for k in acc.COUNTS] == [80, metrics.REMEMBER_FRAMES, 1] + [0] * 7
