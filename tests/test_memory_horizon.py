"""The memory horizon's counting (``metrics.matched_scores``, ``metrics.kept_shares``,
``metrics.hidden_by_the_world``; ``experiments/memory_horizon.py``) and the occlusions the strips
follow (``metrics.occlusions``; ``experiments/occlusion_strip.py``)
against loops and hand-made frames."""

import numpy as np

from e2e_percep_jax import metrics


def test_a_vehicle_is_found_only_by_a_detection_on_its_valid_box():
    gt = np.array([[5.0, 0.0, 0.0, 4.5, 2.0], [10.0, 5.0, 0.3, 4.5, 2.0], [15.0, 0.0, 0.0, 4.5, 2.0]])
    valid = np.array([True, True, False])
    # on the first box; on the third (outside the view); far from every box
    boxes = np.array([[5.0, 0.0, 0.0, 4.5, 2.0], [15.0, 0.0, 0.0, 4.5, 2.0], [-8.0, -8.0, 0.0, 4.5, 2.0]])
    found = metrics.matched_scores(boxes, np.array([0.9, 0.8, 0.7]), gt, valid, 0.1)
    np.testing.assert_array_equal(found, [0.9, -np.inf, -np.inf])
    none = metrics.matched_scores(np.zeros((0, 5)), np.zeros(0), gt, valid, 0.1)
    np.testing.assert_array_equal(none, [-np.inf] * 3)


def test_one_matching_answers_every_operating_score():
    """On random crowded frames, the boxes whose matched score reaches s are those that matching only the
    detections scoring at least s finds, for every s (what lets the evaluation match a frame once)."""
    rng = np.random.default_rng(0)
    for _ in range(50):
        n, m = rng.integers(1, 8), rng.integers(0, 12)
        gt = np.column_stack(
            [rng.uniform(-6, 6, (n, 2)), rng.uniform(-np.pi, np.pi, n), np.full(n, 4.5), np.full(n, 2.0)]
        )
        near = gt[rng.integers(0, n, m)] + np.column_stack(
            [rng.normal(0, 1.5, (m, 2)), rng.normal(0, 0.3, m), np.zeros((m, 2))]
        )
        scores = rng.choice([0.2, 0.5, 0.5, 0.7, 0.9], m)  # ties included
        valid = rng.uniform(size=n) < 0.8
        best = metrics.matched_scores(near, scores, gt, valid, 0.1)
        for s in (0.0, 0.2, 0.5, 0.6, 0.9, 1.0):
            keep = scores >= s
            alone = metrics.matched_scores(near[keep], scores[keep], gt, valid, 0.1) > -np.inf
            np.testing.assert_array_equal(best >= s, alone)


def _looped(found, in_view, followed, subset):
    """Shares [K] by counting box by box."""
    d, k, n = found.shape
    shares = []
    for j in range(k):
        boxes = hits = 0
        for i in range(d):
            for v in range(n):
                if in_view[i, j, v] and followed[i, v] and subset[i, j, v]:
                    boxes += 1
                    hits += found[i, j, v]
        shares.append(hits / boxes if boxes else np.nan)
    return np.array(shares)


def test_the_shares_equal_a_box_by_box_count():
    rng = np.random.default_rng(3)
    d, k, n = 6, 4, 7
    hidden, seen, in_view, standing = (rng.random((d, k, n)) < p for p in (0.4, 0.8, 0.7, 0.5))
    followed = rng.random((d, n)) < 0.6
    in_view[:, 2] = False  # a k without a box: NaN
    found = {"memory": hidden, "sight": seen}
    result = metrics.kept_shares(found, in_view, followed, standing, num_resamples=50)
    for name, subset in (("standing", standing), ("moving", ~standing), ("all", np.ones_like(standing))):
        for run, found_by_run in found.items():
            np.testing.assert_allclose(result[name][run], _looped(found_by_run, in_view, followed, subset))
        boxes = [(in_view & followed[:, None] & subset)[:, j].sum() for j in range(k)]
        assert result[name]["boxes"] == boxes
    assert np.isnan(result["all"]["memory"][2]) and np.all(np.isnan(result["all"]["memory_interval95"][2]))


def test_drives_that_all_agree_give_an_interval_of_one_point():
    rng = np.random.default_rng(4)
    k, n = 3, 5
    one = [rng.random((1, k, n)) < 0.5 for _ in range(4)]
    hidden, seen, in_view, standing = (np.repeat(x, 8, axis=0) for x in one)
    followed = np.ones((8, n), bool)
    found = {"memory": hidden, "sight": seen}
    result = metrics.kept_shares(found, in_view, followed, standing, num_resamples=100)
    for name in ("standing", "moving", "all"):
        for run in ("memory", "sight"):
            low, high = np.array(result[name][f"{run}_interval95"]).T
            np.testing.assert_allclose(low, result[name][run])
            np.testing.assert_allclose(high, result[name][run])


def test_the_drives_are_chosen_by_a_box_by_box_count_of_what_the_world_hides():
    rng = np.random.default_rng(5)
    d, t, n, last_seen = 5, 9, 6, 3
    lidar, camera, valid = (rng.random((d, t, n)) < p for p in (0.5, 0.3, 0.8))
    want = [
        sum(
            valid[i, j, v] and not (lidar[i, j, v] or camera[i, j, v]) and lidar[i, last_seen, v]
            for j in range(last_seen + 1, t)
            for v in range(n)
        )
        for i in range(d)
    ]
    np.testing.assert_array_equal(metrics.hidden_by_the_world(lidar, camera, valid, last_seen), want)


def _occlusions_looped(group, valid, score, min_hidden):
    lidar, remembered = metrics.GROUPS.index("lidar"), metrics.GROUPS.index("remembered")
    found = []
    t_len, n = group.shape
    for slot in range(n):
        for t in range(1, t_len):
            if valid[t - 1, slot] and group[t - 1, slot] == lidar and valid[t, slot] and group[t, slot] == remembered:
                h = 0
                while t + h < t_len and valid[t + h, slot] and group[t + h, slot] == remembered:
                    h += 1
                if h >= min_hidden:
                    found.append((slot, t, h, score[t - 1, slot], list(score[t : t + h, slot])))
    return found


def test_occlusions_are_the_remembered_stretches_right_after_the_lidar_by_hand_and_by_a_loop():
    lidar, camera, remembered, unseen = range(4)
    group = np.array(
        [
            [lidar, lidar, remembered, remembered, remembered, lidar, remembered, remembered],
            [unseen, camera, remembered, remembered, remembered, remembered, remembered, remembered],
        ]
    ).T  # [T, N]: slot 1 was last seen by the camera, never hidden after the lidar
    valid = np.ones_like(group, bool)
    score = np.arange(16, dtype=float).reshape(8, 2)
    events = metrics.occlusions(group, valid, score, min_hidden=2)
    assert [(e.slot, e.frame, e.hidden, e.score_before) for e in events] == [(0, 2, 3, 2.0), (0, 6, 2, 10.0)]
    np.testing.assert_array_equal(events[0].scores, [4.0, 6.0, 8.0])
    assert [(e.frame, e.hidden) for e in metrics.occlusions(group, valid, score, min_hidden=3)] == [(2, 3)]
    valid[3, 0] = False  # out of view in the middle: the stretch ends there
    assert [(e.frame, e.hidden) for e in metrics.occlusions(group, valid, score, min_hidden=1)] == [(2, 1), (6, 2)]

    rng = np.random.default_rng(5)
    for _ in range(30):
        group = rng.choice(4, size=(40, 6), p=[0.3, 0.1, 0.5, 0.1])
        valid = rng.random((40, 6)) < 0.9
        score = rng.random((40, 6))
        got = [
            (e.slot, e.frame, e.hidden, e.score_before, list(e.scores))
            for e in metrics.occlusions(group, valid, score, 2)
        ]
        assert got == _occlusions_looped(group, valid, score, 2)
