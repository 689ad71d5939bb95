"""The table of the end-to-end variants against the modular pipeline, from hand-built metrics.json files:
cells are the runs' own numbers (mean over seeds), towns come training town first, and evaluations under
different protocols are refused."""

import json
import os
import subprocess
import sys

import pytest
from helpers import ROOT, load_experiment

compare = load_experiment("compare")

IOUS, SUBSETS = (
    ("0.1", "0.3", "0.5", "0.7"),
    ("all", "lidar", "camera_only", "remembered", "unseen"),
)  # as evaluate writes them


def _metrics(ap, location_m, town=0, eval_frames=100, pose_defined=True):
    """A minimal metrics.json: every AP equal to ``ap`` (fraction), pose errors from ``location_m``."""
    pose = lambda v: {"mean": v, "median": v} if pose_defined else {"mean": float("nan"), "median": float("nan")}
    return {
        "label": "x",
        "checkpoint_step": 10,
        "config": {
            "world": {"town_seed": 0},
            "data": {"image_size": 32},
            "train": {"num_steps": 10, "seed": 0},
            "eval": {"town_seed": town, "num_steps": eval_frames},
        },
        "detection": {
            "ap": {iou: {s: ap for s in SUBSETS} for iou in IOUS},
            "num_gt": {"all": 50 + town, "lidar": 42, "camera_only": 1, "remembered": 2, "unseen": 5 + town},
        },
        "pose": {"location_m": pose(location_m), "heading_rad": pose(0.5), "speed_mps": pose(1.0)},
        "baseline": {
            "pose": {
                "location_m": {"mean": 99.0, "median": 99.0},
                "heading_rad": {"mean": 1.5, "median": 1.5},
                "speed_mps": {"mean": 3.0, "median": 3.0},
            }
        },
    }


def _write(path, metrics):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(metrics, f)


@pytest.fixture
def runs(tmp_path):
    sweep, base = tmp_path / "sweep", tmp_path / "baselines"
    _write(sweep / "full-seed0" / "eval" / "metrics.json", _metrics(0.50, 10.0))
    _write(sweep / "full-seed1" / "eval" / "metrics.json", _metrics(0.70, 20.0))
    _write(sweep / "full-seed0" / "eval_town7" / "metrics.json", _metrics(0.30, 40.0, town=7))
    _write(base / "detector" / "eval" / "metrics.json", _metrics(0.25, 0.0, pose_defined=False))
    return str(sweep), str(base)


def _cells(text, row):
    line = next(ln for ln in text.splitlines() if ln.startswith(f"| {row} |"))
    return [c.strip() for c in line.strip("|").split("|")][1:]


def test_cells_are_the_seed_means_per_town(runs):
    text = compare.table(compare.collect(*runs))
    header = next(ln for ln in text.splitlines() if ln.startswith("| metric"))
    assert [c.strip() for c in header.strip("|").split("|")][1:] == ["full", "detector", "constant pose"]
    assert _cells(text, "AP@0.5 all (%)") == ["60.0 / 30.0", "25.0 / n/a", "0.0 / 0.0"]
    assert _cells(text, "location mean (m)") == ["15.0 / 40.0", "n/a / n/a", "99.0 / 99.0"]
    assert (
        "Towns 0 / 7" in text
        and "full 2/1, detector 1/0" in text
        and "town 7 all 57, lidar 42, camera only 1, remembered 2, unseen 12" in text
    )


def test_different_protocols_are_refused_by_name(runs):
    sweep, base = runs
    _write(os.path.join(base, "tracker", "eval", "metrics.json"), _metrics(0.3, 1.0, eval_frames=200))
    with pytest.raises(ValueError, match=r"tracker.*differ in eval"):
        compare.check_comparable(compare.collect(sweep, base))


@pytest.mark.slow
def test_launcher_writes_the_table_and_names_bad_flags(runs, tmp_path):
    out = tmp_path / "table.md"
    cmd = [sys.executable, os.path.join(ROOT, "experiments", "compare.py")]
    ok = subprocess.run(
        cmd + [f"--sweep_dir={runs[0]}", f"--baselines_dir={runs[1]}", f"--out={out}"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert ok.returncode == 0 and out.read_text() == compare.table(compare.collect(*runs)), ok.stderr
    bad = subprocess.run(cmd + [f"--sweep_dir={tmp_path / 'missing'}"], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and bad.stderr.strip().startswith("error: --sweep_dir"), bad.stderr


@pytest.mark.parametrize(
    "comparable, refused",
    [
        # An evaluation written before a config field existed equals one that writes the field's default,
        # and still differs from one that sets it otherwise.
        ({"batches_per_drive": 1}, {"batches_per_drive": 4}),
        # The place stream trains the belief head alone: a pipeline trained without it compares with a model
        # trained with it, and not once another data field differs too.
        ({"place_frames": 32}, {"place_frames": 32, "seq_len": 7}),
    ],
    ids=["a field added since compares as its default", "the place stream alone does not part them"],
)
def test_the_tracker_compares_with_the_sweep_unless_its_data_differs(runs, comparable, refused):
    sweep, base = runs
    for data in (comparable, refused):
        tracker = _metrics(0.3, 1.0)
        tracker["config"]["data"].update(data)
        _write(os.path.join(base, "tracker", "eval", "metrics.json"), tracker)
        if data is comparable:
            compare.check_comparable(compare.collect(sweep, base))
        else:
            with pytest.raises(ValueError, match=r"tracker.*differ in data"):
                compare.check_comparable(compare.collect(sweep, base))
