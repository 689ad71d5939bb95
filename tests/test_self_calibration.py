"""The self-calibration report's counting (``experiments/self_calibration.py``) against loops over drives and
frames: the frame from which an estimate stays within 20 % of its drive's truth, and the share of frames
inside a 95 % region with its interval over drives."""

import numpy as np
from helpers import load_experiment

from e2e_percep_jax import calibration

self_calibration = load_experiment("self_calibration")


def test_the_settled_frame_and_shares_equal_a_frame_by_frame_loop():
    rng = np.random.default_rng(2)
    drives, frames = 12, 40
    truth = rng.choice([-1.0, 1.0], drives) * rng.uniform(0.5, 2.0, drives)
    # estimates that wander into and out of the band around the truth, some ending outside it
    estimate = truth[:, None] * (1.0 + rng.normal(0.0, 0.25, (drives, frames)).cumsum(1) / np.arange(1, frames + 1))
    estimate[0, -1] = 1.5 * truth[0]  # a drive that ends outside
    at_frames = [1, 10, frames]
    report = self_calibration._report(estimate, truth, at_frames)
    for w in range(drives):
        within = [abs(estimate[w, t] - truth[w]) <= 0.2 * abs(truth[w]) for t in range(frames)]
        settled = None
        for t in range(frames):  # the first frame from which every later frame is within
            if all(within[t:]):
                settled = t
                break
        assert report["settled_frame"][w] == settled, w
    for f in at_frames:
        count = sum(abs(estimate[w, f - 1] - truth[w]) <= 0.2 * abs(truth[w]) for w in range(drives))
        assert report["share_within_20pct"][str(f)] == count / drives
    settled = report["settled_frame"]
    assert None in settled and 0 in settled and any(s not in (None, 0) for s in settled)  # each case occurs


def test_the_coverage_counts_frames_inside_the_region_and_brackets_it_over_drives():
    rng = np.random.default_rng(4)
    drives, frames = 10, 50
    squared = rng.chisquare(2, (drives, frames)) * rng.uniform(0.6, 1.6, (drives, 1))  # drives differ in spread
    squared[rng.random((drives, frames)) < 0.1] = np.nan  # frames left out
    chi2 = calibration.CHI2_95[2]
    got = self_calibration._coverage(squared, chi2)
    inside = counted = 0
    for w in range(drives):
        for t in range(frames):
            if not np.isnan(squared[w, t]):
                counted += 1
                inside += squared[w, t] <= chi2
    assert got["share"] == inside / counted
    low, high = got["interval95"]
    assert low < got["share"] < high
    # every drive alike: the interval closes on the share
    same = self_calibration._coverage(np.tile(squared[:1], (drives, 1)), chi2)
    assert same["interval95"][0] == same["interval95"][1] == same["share"]
