"""Seed sweeps on the tiny config: the same seed gives identical metrics, a rerun skips finished runs,
and the summary is the mean ± std of the runs' own metrics."""

import glob
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from helpers import ROOT

from e2e_percep_jax.summary import summary_metrics

TINY = ["--config=tiny", "--train.num_steps=4", "--train.checkpoint_every=2", "--eval.num_frames=20"]


def _sweep(sweep_dir, *argv):
    cmd = [sys.executable, os.path.join(ROOT, "experiments", "sweep.py"), f"--sweep_dir={sweep_dir}", *TINY, *argv]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=1200)


def _metrics(sweep_dir, name, evaluation="eval"):
    with open(os.path.join(sweep_dir, name, evaluation, "metrics.json")) as f:
        return json.load(f)


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
    a, b = tmp_path_factory.mktemp("a"), tmp_path_factory.mktemp("b")
    first = _sweep(a, "--seeds=0,1", "--variants=full", "--parallel=2")
    assert first.returncode == 0, first.stdout + first.stderr
    shutil.copy(os.path.join(a, "motion_model.json"), b)  # the same fit: the second sweep need not repeat it
    again = _sweep(b, "--seeds=0", "--variants=full")
    assert again.returncode == 0, again.stdout + again.stderr
    return a, b


@pytest.mark.slow
def test_same_seed_gives_identical_metrics(sweeps):
    a, b = sweeps
    m_a, m_b = _metrics(a, "full-seed0"), _metrics(b, "full-seed0")
    assert summary_metrics(m_a) == summary_metrics(m_b)
    assert m_a["detection"]["pr_curves"] == m_b["detection"]["pr_curves"]
    assert summary_metrics(m_a) != summary_metrics(_metrics(a, "full-seed1"))  # seeds matter


@pytest.mark.slow
def test_the_sweep_fits_the_motion_model_once_for_all_its_runs(sweeps):
    a, _ = sweeps
    with open(os.path.join(a, "motion_model.json")) as f:
        fitted = f.read()
    for name in ("full-seed0", "full-seed1"):
        with open(os.path.join(a, name, "motion_model.json")) as f:
            assert f.read() == fitted
        with open(os.path.join(a, name, "main.log")) as f:
            assert "fitting the motion model" not in f.read()  # the run found its copy


@pytest.mark.slow
def test_rerun_skips_finished_runs(sweeps):
    a, _ = sweeps
    before = os.path.getmtime(os.path.join(a, "full-seed0", "eval", "metrics.json"))
    rerun = _sweep(a, "--seeds=0,1", "--variants=full")
    assert rerun.returncode == 0 and "2 already finished" in rerun.stdout
    assert os.path.getmtime(os.path.join(a, "full-seed0", "eval", "metrics.json")) == before


@pytest.mark.slow
def test_summary_is_mean_and_std_of_the_runs(sweeps):
    a, _ = sweeps
    with open(os.path.join(a, "summary.json")) as f:
        summary = json.load(f)["summary"]["full"]
    rows = [summary_metrics(_metrics(a, f"full-seed{s}")) for s in (0, 1)]
    loc = np.array([r["location mean (m)"] for r in rows])
    np.testing.assert_allclose(summary["location mean (m)"][:2], [loc.mean(), loc.std()], rtol=1e-12)
    assert os.path.exists(os.path.join(a, "summary.md"))


@pytest.mark.slow
def test_held_out_towns_and_baselines_join_a_finished_sweep_without_retraining(sweeps):
    """Grown by held-out towns and a modular baseline, a finished sweep trains nothing of its own again:
    each run is evaluated on the new town and on its own from the known start, dead reckoning beside it on
    the sweep's motion model, and each protocol gets its table of its methods. (The baselines that train go
    through the sweep by the same commands; ``test_baselines`` trains and evaluates them from their
    launcher, and checks which protocols the sweep gives the pose regressor.)"""
    a, _ = sweeps
    run = os.path.join(a, "full-seed0")
    before = {p: os.path.getmtime(os.path.join(run, p)) for p in ("eval/metrics.json", "metrics.jsonl")}
    grown = (
        "--seeds=0",
        "--variants=full",
        "--held_out_towns=3",
        "--training_town_known_start",
        "--baselines=dead_reckoning",
    )
    result = _sweep(a, *grown)
    assert result.returncode == 0 and "1 runs, 0 already finished" in result.stdout, result.stdout + result.stderr
    assert {p: os.path.getmtime(os.path.join(run, p)) for p in before} == before  # no training, no overwrite
    held_out = _metrics(a, "full-seed0", "eval_town3_known_start")
    assert held_out["config"]["eval"]["town_seed"] == 3 and held_out["config"]["eval"]["known_start"]
    assert held_out["checkpoint_step"] == 4
    assert held_out["detection"]["num_gt"] != _metrics(a, "full-seed0")["detection"]["num_gt"]  # another town
    own_town = _metrics(a, "full-seed0", "eval_known_start")
    assert own_town["config"]["eval"]["town_seed"] == 0 and own_town["config"]["eval"]["known_start"]
    base = "baselines-seed0"
    evaluated = {
        os.path.relpath(os.path.dirname(p), os.path.join(a, base))
        for p in glob.glob(os.path.join(a, base, "*", "eval*", "metrics.json"))
    }
    assert evaluated == {"dead_reckoning/eval_known_start", "dead_reckoning/eval_town3_known_start"}
    with (
        open(os.path.join(a, "motion_model.json")) as f,
        open(os.path.join(a, base, "dead_reckoning", "motion_model.json")) as g,
    ):
        assert f.read() == g.read()
    with open(os.path.join(a, "summary_town3_known_start.json")) as f:
        summary = json.load(f)["summary"]
    assert set(summary) == {"full", "dead_reckoning"}
    assert summary["full"]["location mean (m)"][0] == summary_metrics(held_out)["location mean (m)"]
    with open(os.path.join(a, "summary_known_start.json")) as f:
        assert set(json.load(f)["summary"]) == {"full", "dead_reckoning"}
    with open(os.path.join(a, "summary.json")) as f:
        assert set(json.load(f)["summary"]) == {"full"}
    again = _sweep(a, *grown)
    assert again.returncode == 0 and "1 runs, 1 already finished" in again.stdout


@pytest.mark.slow
def test_bad_sweep_flags_are_named(tmp_path):
    for argv, flag in (
        (["--seeds=0,x"], "--seeds"),
        (["--variants=full,bogus"], "--variants"),
        (["--parallel=0"], "--parallel"),
        (["--baselines=detector,bogus"], "--baselines"),
        (["--held_out_towns=0"], "--held_out_towns"),
        (["--training_town_known_start", "--eval.known_start"], "--training_town_known_start"),
        (["--data.image_size=48"], "--data.image_size"),
    ):
        result = _sweep(tmp_path, *argv)
        assert result.returncode == 1 and result.stderr.strip().startswith(f"error: {flag}"), result.stderr
