"""experiments/memory_ceiling.py: which remembered boxes belong to a vehicle found before it was hidden,
counted on a hand-built drive."""

import numpy as np
from helpers import load_experiment

from e2e_percep_jax import evaluate as eval_lib
from e2e_percep_jax import metrics

memory_ceiling = load_experiment("memory_ceiling")
LIDAR, REMEMBERED = metrics.GROUPS.index("lidar"), metrics.GROUPS.index("remembered")


def test_a_remembered_box_counts_as_found_before_only_if_its_vehicle_was_detected_at_the_operating_score():
    """35 frames. Car A: detected (0.9) while the lidar sees it (frames 0-9), then remembered (10-34).
    Car C: seen 0-9 but detected only at 0.3, under the operating score, then remembered (10-19), then
    gone. Car B: seen and detected (0.8) throughout. Of the 35 remembered boxes, A's 25 were found before
    (the last detection, frame 9, lies within 30 frames of all of them) and C's 10 were not; none is found
    now; of the 55 boxes the lidar sees, C's 10 are missed."""
    ego = np.array([0.0, 0.0, 1.0, 0.0, 0.0])
    frames = []
    for k in range(35):
        a, b, c = [5.0 + 0.2 * k, 3.5, 0.0, 4.5, 1.9], [10.0, -4.0, 0.0, 4.5, 1.9], [-6.0, 6.0, 0.0, 4.5, 1.9]
        valid = np.array([True, True, k < 20])
        group = np.array([LIDAR if k < 10 else REMEMBERED, LIDAR, LIDAR if k < 10 else REMEMBERED])
        detected = ([a, c] if k < 10 else []) + [b]
        scores = ([0.9, 0.3] if k < 10 else []) + [0.8]
        frames.append(
            eval_lib.RecordedFrame(np.array(detected), np.array(scores), ego, np.array([a, b, c]), valid, group)
        )
    counts = memory_ceiling.ceiling([frames], score_threshold=0.5)
    assert {k: counts[k] for k in ("remembered", "remembered_found_before", "remembered_found_now")} == {
        "remembered": 35,
        "remembered_found_before": 25,
        "remembered_found_now": 0,
    }
    assert (counts["lidar"], counts["lidar_found_now"]) == (55, 45)
    assert counts["share_remembered_found_before"] == 25 / 35
