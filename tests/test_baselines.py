"""Modular baselines (e2e_percep_jax/baselines.py, experiments/baselines.py): no memory in the single-frame
models, their losses against NumPy, the tracker and dead reckoning through the online evaluation with an
oracle, and the launcher end to end.

Cost: the launcher runs in a subprocess started first (it overlaps the in-process tests); in this process
one evaluation program is compiled (the oracle) and reused by the tracker and dead-reckoning runs.
"""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import EXACT_PLANT, ROOT, TINY, np_focal, np_smooth_l1, odometry_model, synthetic_batch

from e2e_percep_jax import baselines, config, ego_motion, model, tracking
from e2e_percep_jax import evaluate as eval_lib
from e2e_percep_jax.sim import batch as batch_lib
from e2e_percep_jax.sim import rollout
from e2e_percep_jax.sim import town as town_lib

LAUNCHER = [sys.executable, os.path.join(ROOT, "experiments", "baselines.py"), "--config=tiny"]
# The tracker trains the detector's run first; the pose regressor trains by the same code (its loss and
# model are tested in this process), left out to save its two compilations.
CLI_FLAGS = ["--baseline=tracker,dead_reckoning", "--train.num_steps=4", "--eval.num_frames=20", "--video_frames=0"]


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    """The launcher, started at once; yields a function that waits for it and for a
    second, identical command (which must find everything done)."""
    workdir = str(tmp_path_factory.mktemp("baselines"))
    proc = subprocess.Popen(
        LAUNCHER + CLI_FLAGS + [f"--workdir={workdir}"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    result = {}

    def wait():
        if not result:
            first, _ = proc.communicate(timeout=600)
            assert proc.returncode == 0, first[-3000:]
            again = subprocess.run(
                LAUNCHER + CLI_FLAGS + [f"--workdir={workdir}"], capture_output=True, text=True, timeout=300
            )
            assert again.returncode == 0, again.stdout + again.stderr
            result.update(workdir=workdir, first=first, again=again.stdout)
        return result

    yield wait
    if proc.poll() is None:
        proc.kill()


# ----------------------------------------------------------------------------- single-frame models


@pytest.mark.slow
def test_single_frame_output_ignores_other_frames_while_the_filter_remembers(cli_run):
    """Frames other than t replaced by new random images: the baselines' outputs at t are unchanged (bit for
    bit), the perception model's latent at t is not (it filters through time)."""
    cfg, t = TINY, 2
    batch, other = synthetic_batch(0, cfg), synthetic_batch(1, cfg)
    keep_t = lambda k: np.where((np.arange(cfg.data.seq_len + 1) == t)[None, :, None, None, None], batch[k], other[k])
    changed = {k: keep_t(k) for k in ("camera", "lidar")}
    for head in baselines.HEADS:
        params = baselines.init_params(jax.random.PRNGKey(0), cfg, head)
        image = jax.ShapeDtypeStruct((1, 32, 32, 3), jnp.uint8)  # flax's own init: the same tree and shapes
        flax_init = jax.eval_shape(
            lambda k, x: baselines.build_model(cfg, head).init(k, x, x), jax.random.PRNGKey(0), image
        )
        assert jax.tree.map(np.shape, params) == jax.tree.map(lambda x: x.shape, flax_init)
        before = baselines.predict(params, batch["camera"], batch["lidar"], cfg, head)
        after = baselines.predict(params, changed["camera"], changed["lidar"], cfg, head)
        for k in before:
            np.testing.assert_array_equal(after[k][:, t], before[k][:, t], err_msg=f"{head} {k}")
            assert not np.allclose(after[k][:, t + 1], before[k][:, t + 1]), (head, k)  # the inputs do matter
    params = model.init_params(jax.random.PRNGKey(0), cfg)
    z = jax.jit(lambda c, li: model.filter_sequence(params, c, li, batch["action"], None, cfg)["z2"][:, t])
    assert np.max(np.abs(z(changed["camera"], changed["lidar"]) - z(batch["camera"], batch["lidar"]))) > 1e-3


def test_baseline_losses_are_the_perception_loss_terms_in_numpy():
    """Each head's loss is the perception loss's own terms (focal + 0.1 smooth-L1 at positives, or the
    smooth-L1 pose loss in normalised units), per sequence, recomputed in NumPy from the predictions."""
    cfg, batch = TINY, synthetic_batch(3, TINY)
    b, w = batch["camera"].shape[0], TINY.train.perception_weight
    for head, names in (("detection", {"det_cls", "det_reg"}), ("pose", {"pose"})):
        params = baselines.init_params(jax.random.PRNGKey(1), cfg, head)
        total, metrics = baselines.loss_fn(params, batch, None, cfg, head)
        pred = jax.tree.map(
            lambda x: np.asarray(x, np.float64), baselines.predict(params, batch["camera"], batch["lidar"], cfg, head)
        )
        if head == "detection":
            positive = batch["det_cls"] > 0.5
            want = {
                "det_cls": w * np.sum(np_focal(pred["det_logit"], batch["det_cls"])) / b,
                "det_reg": w
                * 0.1
                * np.sum(np.where(positive, np_smooth_l1(pred["det_reg"] - batch["det_reg"]), 0))
                / b,
            }
        else:
            target = (batch["pose"] - [200, 200, 0, 0, 0]) / [100, 100, 1, 1, 10]
            want = {"pose": w * np.sum(np_smooth_l1(pred["pose_normalised"] - target)) / b}
        assert set(metrics) == names | {"total"}
        for k, v in want.items():
            np.testing.assert_allclose(metrics[k], v, rtol=2e-4, err_msg=k)
        np.testing.assert_allclose(total, sum(want.values()), rtol=2e-4)
        assert np.isfinite(total) and all(v > 0 for v in want.values())


# ----------------------------------------------------------------------------- tracker and dead reckoning


def oracle_heads(outputs, frame):
    """The world's own PIXOR targets as detections (score 1 on every vehicle in view); no pose."""
    return outputs.replace(det_cls=frame["det_cls"], det_reg=frame["det_reg"])


ORACLE_CFG = config.replace(TINY, world=dict(num_vehicles=100), eval=dict(num_frames=160, num_worlds=2, chunk_steps=20))


# Measurements trusted (the filter follows each detection) and every track born at once: the tracks'
# boxes are the detections', and tracks coasting after a miss score below every detection (0.9^misses).
def test_the_tracker_host_reports_no_track_that_coasts_out_of_the_view():
    """A car detected at 16, 17.5 and 19 m ahead, then lost: its track coasts on at 1.5 m a frame and is
    reported while its centre lies in the bird-eye view (20 m ahead), and not once it has left it, though
    the tracker still holds it."""
    post = baselines.tracker_host(TRUSTING)(0)
    ego = np.array([0.0, 0.0, 1.0, 0.0, 0.0])
    shown = []
    for x in (16.0, 17.5, 19.0, None, None):
        boxes = np.zeros((0, 5)) if x is None else np.array([[x, 0.0, 0.0, 4.5, 1.9]])
        out, scores, _ = post(boxes, np.full(len(boxes), 0.9), None, ego)
        shown.append(out[:, 0].round(1).tolist())
    assert shown == [[16.0], [17.5], [19.0], [], []], shown


TRUSTING = tracking.TrackerConfig(min_hits=1, meas_pos_std_m=1e-3, meas_yaw_std_rad=1e-3, meas_size_std_m=1e-3)


@pytest.fixture(scope="module")
def oracle_eval(tmp_path_factory):
    """``evaluate`` with the oracle frame function (one compile) and any host function."""

    def run(host_fn, name):
        return eval_lib.evaluate(
            ORACLE_CFG,
            {},
            str(tmp_path_factory.mktemp(name)),
            video_frames=0,
            num_examples=0,
            perceiver=baselines.SingleFramePerceiver(ORACLE_CFG, None),
            heads=oracle_heads,
            host_fn=host_fn,
            log=lambda _: None,
        )

    return run


@pytest.mark.slow
def test_tracker_on_oracle_detections_keeps_their_ap(oracle_eval):
    plain = oracle_eval(None, "plain")["detection"]
    tracked = oracle_eval(baselines.tracker_host(TRUSTING), "tracked")["detection"]
    assert tracked["num_gt"] == plain["num_gt"] and plain["num_gt"]["lidar"] > 100
    assert tracked["ap"]["0.5"]["lidar"] >= 0.99, tracked["ap"]
    for iou in ("0.1", "0.5", "0.7"):
        for subset in ("all", "lidar"):
            assert tracked["ap"][iou][subset] >= plain["ap"][iou][subset] - 1e-3, (
                iou,
                subset,
                tracked["ap"],
                plain["ap"],
            )


def _recorded_drive():
    """35 frames seen from a standing ego: car A drives 0.2 m a frame, detected (score 0.9) while the lidar
    sees it (frames 0-9), then remembered (frames 10-34: no detection); car B stands, detected (0.8) in
    every frame."""
    frames, ego = [], np.array([0.0, 0.0, 1.0, 0.0, 0.0])
    for k in range(35):
        a, b = [2.0 + 0.2 * k, 3.5, 0.0, 4.5, 1.9], [10.0, -4.0, 0.0, 4.5, 1.9]
        true = np.array([a, b])
        group = [0 if k < 10 else 2, 0]  # metrics.GROUPS: lidar, remembered
        detected = np.array([a, b] if k < 10 else [b])
        scores = np.array([0.9, 0.8] if k < 10 else [0.8])
        frames.append(eval_lib.RecordedFrame(detected, scores, ego, true, np.ones(len(true), bool), np.array(group)))
    return [frames]


def test_the_tracker_tuning_keeps_the_hidden_car_as_long_as_it_is_remembered():
    """The hidden car coasts on its velocity: kept 10 frames (max_age 10), 10 of its 25 remembered boxes are
    found (AP@0.1 0.4: every reported box a true one); kept 30 or 50 frames, all 25 (AP 1). The tuning keeps
    the first of the best (grid order) and reports every candidate."""
    grid = dict(max_age=(10, 30, 50), score_decay=(0.9, 1.0), confidence=("last",))
    chosen, rows = baselines.tune_tracker(_recorded_drive(), grid, log=lambda _: None)
    assert len(rows) == 6
    for r in rows:
        expected = 0.4 if r["max_age"] == 10 else 1.0
        assert r["ap"]["0.1"]["remembered"] == pytest.approx(expected, abs=1e-9), r
    assert (chosen.max_age, chosen.score_decay, chosen.confidence) == (30, 0.9, "last")
    assert chosen.min_hits == tracking.TrackerConfig().min_hits  # what is not tuned keeps its default


def test_the_tracker_tuning_on_drives_without_a_box_keeps_the_first_setting():
    """No box, no AP (NaN): every candidate ties, and the grid's first is kept."""
    ego, empty = np.array([0.0, 0.0, 1.0, 0.0, 0.0]), np.zeros((0, 5))
    frame = eval_lib.RecordedFrame(empty, np.zeros(0), ego, empty, np.zeros(0, bool), np.zeros(0, np.int64))
    grid = dict(max_age=(10, 30), score_decay=(0.9,), confidence=("last", "mean"))
    chosen, rows = baselines.tune_tracker([[frame] * 5], grid, log=lambda _: None)
    assert (chosen.max_age, chosen.confidence) == (10, "last") and len(rows) == 4


@pytest.mark.slow
def test_wheel_odometry_without_noise_or_bias_follows_the_true_path(oracle_eval):
    """Exact sensors: the reckoned pose is the true one up to float32 rounding of ~400 m coordinates; with
    a wheel-radius error, a gyro bias and noise the error is positive and grows with time since the start."""
    exact = oracle_eval(baselines.wheel_odometry_host(0, 0.0, 0.0, 0.0, 0.0), "exact")["pose"]
    assert sum(exact["location_m_by_step"]["count"]) == 160
    assert exact["location_m"]["mean"] < 1e-3 and exact["heading_rad"]["mean"] < 1e-4, exact
    assert exact["speed_mps"]["mean"] < 1e-6
    noisy = oracle_eval(baselines.wheel_odometry_host(0, 0.05, 0.01, 0.5, 0.05), "noisy")["pose"]
    by_step = [m for m, n in zip(noisy["location_m_by_step"]["mean"], noisy["location_m_by_step"]["count"]) if n]
    assert noisy["location_m"]["mean"] > 1e-2 and by_step[-1] > by_step[0], noisy
    assert noisy["speed_mps"]["mean"] > 0.01  # the wheel-radius error scales the reported speed


@pytest.mark.slow
def test_dead_reckoning_on_the_commands_is_exact_in_the_exact_world_and_drifts_under_the_plant(tmp_path):
    """The commands through the exact bicycle (``MotionModel()``) from the true start: the true path (to
    float32 rounding) where the world's plant is exact; metres off where it is not."""

    def run(world, name):
        cfg = config.replace(ORACLE_CFG, world=world, eval=dict(known_start=True, num_frames=400))
        return eval_lib.evaluate(
            cfg,
            {},
            str(tmp_path / name),
            video_frames=0,
            num_examples=0,
            perceiver=baselines.CommandOdometry(cfg, baselines.motion_lib.MotionModel()),
            log=lambda _: None,
        )["pose"]

    exact, plant = run(EXACT_PLANT, "exact"), run({}, "plant")
    assert exact["location_m"]["mean"] < 0.02 and exact["heading_rad"]["mean"] < 1e-3, exact
    assert plant["location_m"]["mean"] > 0.5, plant


@pytest.mark.slow
def test_the_lidar_odometry_baseline_steps_as_the_odometry_follows_a_drive():
    """``CommandOdometry`` with the scans, stepped frame by frame through a world drive (40 frames: eight
    matches) by a motion model with an actuator lag, moves each stream's pose as ``ego_motion.follow`` moves
    it from the same start on the same commands and scans: the drive's first commands set the actuators,
    which then lag behind the commands."""
    cfg = config.replace(TINY, eval=dict(known_start=True))
    model = odometry_model(lag_share=0.5)
    town = town_lib.build_town(cfg.world.town_seed)
    states = jax.jit(batch_lib.warm_up, static_argnames="cfg")(jax.random.PRNGKey(6), town, cfg)
    r = cfg.data.image_size
    _, drive = jax.jit(jax.vmap(lambda s: rollout.drive(s, town, 40, r, scans=True)))(states)
    prev_action = jnp.concatenate([drive["action"][:, :1], drive["action"][:, :-1]], 1)
    prev_action = prev_action.at[:, 0].set(drive["action"][:, 0] * 0.5)  # a first command unlike the next
    start = drive["pose"][:, 0]
    followed, _, _ = jax.jit(ego_motion.follow, static_argnums=0)(model, start, prev_action, drive["lidar_scan"])
    odometry = baselines.CommandOdometry(cfg, model, scans=True)
    step, state = jax.jit(odometry.step, static_argnames="measure"), odometry.init(start.shape[0])
    for t in range(40):
        frame = lambda k: drive[k][:, t]
        state, out = step(
            {},
            state,
            frame("camera"),
            frame("lidar"),
            prev_action[:, t],
            start_pose=start,
            lidar_scan=frame("lidar_scan"),
        )
        np.testing.assert_allclose(out.pose, followed[:, t], rtol=1e-5, atol=1e-4)


# ----------------------------------------------------------------------------- launcher


@pytest.mark.slow
def test_cli_trains_evaluates_and_resumes(cli_run):
    r = cli_run()
    workdir = r["workdir"]
    metrics = {}
    for name, eval_dir in (("tracker", "eval"), ("dead_reckoning", "eval_known_start")):
        with open(os.path.join(workdir, name, eval_dir, "metrics.json")) as f:
            metrics[name] = json.load(f)
        assert metrics[name]["num_frames"] == 20
        with open(os.path.join(workdir, name, eval_dir, "report.md")) as f:
            report = f.read()
        assert f"baseline `{metrics[name]['label']}`" in report and "same variant" not in report
    # The tracker evaluates the detector's run, trained on the detection terms; it trains nothing itself.
    with open(os.path.join(workdir, "detector", "metrics.jsonl")) as f:
        records = [json.loads(line) for line in f]
    assert records[-1]["step"] == 4 and {"det_cls", "det_reg", "total"} <= set(records[-1])
    assert not {"kl", "pose"} & set(records[-1])
    assert os.path.isdir(os.path.join(workdir, "detector", "checkpoints", "4"))
    assert metrics["tracker"]["workdir"] == os.path.join(workdir, "detector")
    assert metrics["tracker"]["checkpoint_step"] == 4
    assert not os.path.exists(os.path.join(workdir, "tracker", "checkpoints"))
    assert not np.isfinite(metrics["tracker"]["pose"]["location_m"]["mean"])  # no pose head: n/a
    assert metrics["dead_reckoning"]["detection"]["ap"]["0.5"]["all"] == 0.0  # no detection: no boxes
    # 10 frames from the true start pose through the fitted motion model: centimetres
    assert 0.0 < metrics["dead_reckoning"]["pose"]["location_m"]["mean"] < 0.5
    assert metrics["dead_reckoning"]["pose"]["known_start"]
    assert os.path.exists(os.path.join(workdir, "dead_reckoning", "motion_model.json"))
    assert r["again"].count("nothing to do") == 2 and "training" not in r["again"], r["again"]
    # The tracker's coasting was tuned once, on drives of another seed, and named in its label.
    with open(os.path.join(workdir, "tracker", "tuning.json")) as f:
        tuning = json.load(f)
    assert tuning["drives"]["seed"] != metrics["tracker"]["config"]["eval"]["seed"]
    assert len(tuning["candidates"]) == np.prod([len(v) for v in baselines.TRACKER_GRID.values()])
    assert f"coasting up to {tuning['chosen']['max_age']} frames" in metrics["tracker"]["label"]
    assert "tuning" not in r["again"]


@pytest.mark.slow
def test_bad_flags_fail_in_one_line_before_any_compile(tmp_path):
    """JAX_LOG_COMPILES=1 logs every compilation to stderr: a one-line stderr means nothing compiled."""
    cases = [
        (["--baseline=detector,kalman"], "--baseline=detector,kalman"),
        (["--world.ego_lag_s=-0.1"], "--world.ego_lag_s=-0.1"),
        (["--data.image_size=48"], "--data.image_size=48"),
    ]
    procs = [
        subprocess.Popen(
            LAUNCHER + flags + [f"--workdir={tmp_path / str(i)}"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=dict(os.environ, JAX_LOG_COMPILES="1"),
        )
        for i, (flags, _) in enumerate(cases)
    ]
    for (flags, text), proc in zip(cases, procs):
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 1 and err.count("\n") == 1 and err.startswith("error: ") and text in err, (
            flags,
            out + err,
        )


def test_a_sweep_evaluates_the_pose_regressor_on_its_training_town_alone():
    """Under a held-out town or the known start the pose regressor (which learned the training town's
    places) is left out; the others are kept, in order."""
    own = config.get_config("tiny")
    everything = ["detector", "pose", "dead_reckoning"]
    assert baselines.evaluated_under(everything, own, own) == everything
    for changed in (dict(town_seed=3, known_start=True), dict(known_start=True)):
        assert baselines.evaluated_under(everything, config.replace(own, eval=changed), own) == [
            "detector",
            "dead_reckoning",
        ]
