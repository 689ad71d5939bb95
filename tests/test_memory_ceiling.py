"""experiments/memory_ceiling.py: which remembered boxes belong to a vehicle found before it was hidden,
and which of those a perceiver keeps, counted on a hand-built drive."""

import numpy as np
from helpers import load_experiment

from e2e_percep_jax import evaluate as eval_lib
from e2e_percep_jax import metrics

memory_ceiling = load_experiment("memory_ceiling")
LIDAR, REMEMBERED = metrics.GROUPS.index("lidar"), metrics.GROUPS.index("remembered")


def test_a_remembered_box_counts_as_found_before_only_if_its_vehicle_was_detected_at_the_operating_score():
    """35 frames, four cars. A: detected (0.9) while the lidar sees it (frames 0-9), then remembered and
    not detected (10-34). B: seen and detected (0.8) throughout. C: seen 0-9 but detected only at 0.3,
    under the operating score, then remembered (10-19), then gone. D: detected (0.9) while seen (0-9),
    then remembered and still detected (0.6) for 5 frames (10-14), then gone. Of the 40 remembered boxes,
    A's 25 and D's 5 were found before (the last detection while seen, frame 9, lies within 30 frames of
    all of them), C's 10 were not; D's 5 are kept; of the 65 boxes the lidar sees, C's 10 are missed."""
    ego = np.array([0.0, 0.0, 1.0, 0.0, 0.0])
    frames = []
    for k in range(35):
        a, b = [5.0 + 0.2 * k, 3.5, 0.0, 4.5, 1.9], [10.0, -4.0, 0.0, 4.5, 1.9]
        c, d = [-6.0, 6.0, 0.0, 4.5, 1.9], [-6.0, -8.0, 0.0, 4.5, 1.9]
        valid = np.array([True, True, k < 20, k < 15])
        hidden = LIDAR if k < 10 else REMEMBERED
        group = np.array([hidden, LIDAR, hidden, hidden])
        detected = ([a, c] if k < 10 else []) + [b] + ([d] if k < 15 else [])
        scores = ([0.9, 0.3] if k < 10 else []) + [0.8] + ([0.9 if k < 10 else 0.6] if k < 15 else [])
        true = np.array([a, b, c, d])
        frames.append(eval_lib.RecordedFrame(np.array(detected), np.array(scores), ego, true, valid, group))
    counts = memory_ceiling.ceiling([frames], score_threshold=0.5)
    names = (
        "remembered",
        "remembered_found_before",
        "remembered_found_now",
        "remembered_kept",
        "lidar",
        "lidar_found_now",
    )
    assert {k: counts[k] for k in names} == dict(zip(names, (40, 30, 5, 5, 65, 55)))
    assert counts["share_found_before_kept"] == 5 / 30
