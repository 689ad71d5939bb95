"""The public inference API: batching, streaming vs the training-time scan, jit/scan inside user code,
and loading a trained run. (Bad arguments and damaged runs are rows of test_bad_input.py.)"""

import dataclasses
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ROOT, run_readme_example

import e2e_percep_jax as e2e
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import ego_motion, pose_belief
from e2e_percep_jax import model as model_lib
from e2e_percep_jax import train as train_lib
from e2e_percep_jax.sim import batch as batch_lib
from e2e_percep_jax.sim import pixor, rollout
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim.motion import MotionModel

CFG = config_lib.get_config("tiny")
R = CFG.data.image_size


@pytest.fixture(scope="module")
def params():
    return model_lib.init_params(jax.random.PRNGKey(0), CFG)


def _inputs(num_streams, num_frames, seed=0):
    rng = np.random.default_rng(seed)
    images = lambda: jnp.asarray(rng.integers(0, 256, (num_streams, num_frames, R, R, 3), np.uint8))
    action = jnp.asarray(rng.uniform(-1, 1, (num_streams, num_frames, 2)).astype(np.float32))
    return images(), images(), action


def _stream(perceiver, params, camera, lidar, prev_action, keys=None):
    """Steps frame by frame in Python; returns the outputs stacked to [B, T, ...]."""
    state, outs = perceiver.init(camera.shape[0]), []
    step = jax.jit(perceiver.step)
    for t in range(camera.shape[1]):
        state, out = step(
            params, state, camera[:, t], lidar[:, t], prev_action[:, t], None if keys is None else keys[t]
        )
        outs.append(out)
    return jax.tree.map(lambda *x: jnp.stack(x, 1), *outs)


@pytest.mark.slow
def test_batch_of_streams_equals_each_stream_alone(params):
    perceiver = e2e.Perceiver(CFG)
    camera, lidar, action = _inputs(3, 4)
    together = _stream(perceiver, params, camera, lidar, action)
    for i in range(3):
        alone = _stream(perceiver, params, camera[i : i + 1], lidar[i : i + 1], action[i : i + 1])
        for k in ("det_cls", "det_reg", "pose", "z", "roadmap"):
            got, want = getattr(together, k)[i : i + 1], getattr(alone, k)
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5, err_msg=k)


@pytest.mark.parametrize(
    "variant, pose_head, pose_filter",
    [("full", "belief", "histogram"), ("no_input_recon", "belief", "none"), ("no_roadmap_recon", "regression", "none")],
)
def test_state_and_outputs_hold_what_the_config_has(variant, pose_head, pose_filter):
    """Traced only (``jax.eval_shape``): the step returns a state of ``init``'s structure, with the pose
    belief (``state.pose``) and ``pose_place`` only with the belief head, and the reconstructions the
    variant has; the fields it lacks are None."""
    model = dict(variant=variant, pose_head=pose_head, pose_filter=pose_filter)
    cfg = config_lib.replace(CFG, model=model, data=dict(place_frames=CFG.data.place_frames * (pose_head == "belief")))
    perceiver = e2e.Perceiver(cfg)
    params = jax.eval_shape(lambda: model_lib.init_params(jax.random.PRNGKey(0), cfg))
    camera, lidar, action = (x[:, 0] for x in _inputs(2, 1))
    state = perceiver.init(2)
    stepped, out = jax.eval_shape(perceiver.step, params, state, camera, lidar, action)
    assert jax.tree.structure(stepped) == jax.tree.structure(state)
    belief = pose_head == "belief"
    assert (state.pose is not None) == belief and (out.pose_place is not None) == belief
    for name in ("camera", "lidar", "roadmap"):
        assert (getattr(out, name) is not None) == (name in model_lib.reconstructed_images(variant)), name
    assert out.pose.shape == (2, 5) and out.z.shape == (2, cfg.model.z1_dim + cfg.model.z2_dim)


@pytest.mark.slow
@pytest.mark.parametrize("sampled", [False, True])
def test_streaming_equals_the_training_scan(params, sampled):
    perceiver = e2e.Perceiver(CFG)
    camera, lidar, action = _inputs(2, 5, seed=1)  # action t: applied from frame t to t+1 (training layout)
    key = jax.random.PRNGKey(7) if sampled else None
    scanned = model_lib.filter_sequence(params, camera, lidar, action, key, CFG)
    prev_action = jnp.concatenate([jnp.zeros_like(action[:, :1]), action[:, :-1]], 1)
    keys = None if key is None else jax.random.split(key, 5)  # filter_sequence's per-frame keys
    streamed = _stream(perceiver, params, camera, lidar, prev_action, keys)
    z = jnp.concatenate([scanned["z1"], scanned["z2"]], -1)
    np.testing.assert_allclose(streamed.z, z, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_step_inside_a_users_jit_and_scan(params):
    perceiver = e2e.Perceiver(CFG)
    camera, lidar, action = _inputs(2, 3, seed=2)

    @jax.jit
    def user_rollout(params, camera, lidar, action):
        def body(state, xs):
            state, out = perceiver.step(params, state, *xs)
            return state, out.pose

        xs = tuple(jnp.swapaxes(x, 0, 1) for x in (camera, lidar, action))
        return jax.lax.scan(body, perceiver.init(camera.shape[0]), xs)[1]

    poses = jnp.swapaxes(user_rollout(params, camera, lidar, action), 0, 1)
    streamed = _stream(perceiver, params, camera, lidar, action)
    np.testing.assert_allclose(poses, streamed.pose, rtol=1e-5, atol=1e-4)
    assert poses.shape == (2, 3, 5)


# A motion model unlike the exact bicycle in every part (lag, pedal gain and bias, steering gain and bias,
# understeer), so that a test of the odometry fails if any of them is ignored.
MODEL = MotionModel(
    lag_share=0.6,
    accel_per_pedal_mps2=2.5,
    accel_bias_mps2=0.1,
    steer_gain=1.1,
    steer_bias=0.02,
    understeer_s2pm2=-0.002,
    heading_noise_rad2pm=1e-4,
    position_noise_m2pm=1e-3,
)


def _odometry(start, commands):
    """Poses [T, 5] of MODEL's equations written out here in NumPy float64: from ``start`` [5], the actuators
    set by the first commands, then each frame's commands [T, 2] (frame 0's unused)."""
    x, y, yaw, v = start[0], start[1], np.arctan2(start[3], start[2]), start[4]
    actuator, poses = np.asarray(commands[min(1, len(commands) - 1)], np.float64), [np.array(start, np.float64)]
    for command in commands[1:]:
        actuator = actuator + MODEL.lag_share * (command - actuator)
        v_new = max(v + (MODEL.accel_per_pedal_mps2 * actuator[0] + MODEL.accel_bias_mps2) * 0.1, 0.0)
        ds, v_mid = 0.5 * (v + v_new) * 0.1, 0.5 * (v + v_new)
        tan = np.tan(actuator[1])
        dyaw = ds * (MODEL.steer_gain * tan + MODEL.steer_bias + MODEL.understeer_s2pm2 * tan * v_mid**2) / 2.7
        rear = np.array([x, y]) - 1.35 * np.array([np.cos(yaw), np.sin(yaw)])
        rear = rear + ds * np.array([np.cos(yaw + dyaw / 2), np.sin(yaw + dyaw / 2)])
        yaw, v = yaw + dyaw, v_new
        x, y = rear + 1.35 * np.array([np.cos(yaw), np.sin(yaw)])
        poses.append(np.array([x, y, np.cos(yaw), np.sin(yaw), v]))
    return np.stack(poses)


@pytest.mark.slow
def test_the_known_start_off_the_training_town_is_the_lidar_odometry(params):
    """With a motion model that has the scan matcher's noise, ``measure=False`` moves each stream's pose as
    ``ego_motion.follow`` moves it from the same start on the same commands and lidar scans (a drive of the
    world, 30 frames: six matches), which correct the heading away from the commands' alone; without the
    frame's ``lidar_scan``, or with one of the wrong width on the measured town, the step names it."""
    model = dataclasses.replace(
        MODEL, yaw_bias_std_1pm=0.002, yaw_gain_std=0.03, yaw_noise_rad2pm=1e-6, scan_heading_noise_rad=0.002
    )
    perceiver = e2e.Perceiver(CFG, model)
    assert perceiver.lidar_odometry
    town = town_lib.build_town(CFG.world.town_seed)
    states = jax.jit(batch_lib.warm_up, static_argnames="cfg")(jax.random.PRNGKey(5), town, CFG)
    _, drive = jax.jit(jax.vmap(lambda s: rollout.drive(s, town, 30, R, scans=True)))(states)
    b = drive["pose"].shape[0]
    prev_action = jnp.concatenate([drive["action"][:, :1], drive["action"][:, :-1]], 1)
    start = drive["pose"][:, 0]
    followed, _, _ = jax.jit(ego_motion.follow, static_argnums=0)(model, start, prev_action, drive["lidar_scan"])
    reckoned, _, _ = jax.jit(ego_motion.follow, static_argnums=0)(model, start, prev_action, None)
    step, state = jax.jit(perceiver.step, static_argnames="measure"), perceiver.init(b)
    first_frame = (params, state, drive["camera"][:, 0], drive["lidar"][:, 0], prev_action[:, 0])
    for bad in (dict(start_pose=start, measure=False), dict(lidar_scan=jnp.zeros((b, 359)))):
        with pytest.raises(ValueError, match="lidar_scan"):
            step(*first_frame, **bad)
    for t in range(30):
        frame = lambda k: drive[k][:, t]
        state, out = step(
            params,
            state,
            frame("camera"),
            frame("lidar"),
            prev_action[:, t],
            start_pose=start,
            measure=False,
            lidar_scan=frame("lidar_scan"),
        )
    np.testing.assert_allclose(out.pose, followed[:, -1], rtol=1e-5, atol=1e-4)
    assert np.abs(np.asarray(followed[:, -1, 2:4] - reckoned[:, -1, 2:4])).max() > 1e-4  # the scans took part


@pytest.mark.slow
def test_pose_belief_through_the_api_known_start_and_global(params):
    """The belief head's outputs: ``pose_place`` is a distribution over the cells. With ``start_pose`` and
    ``measure=False`` the pose is the known start on a stream's first frame, then that start moved by the
    commands through the perceiver's motion model alone (an independent NumPy integration), whatever the
    images; with the measurement, the first frame's belief lies on the cells around the start."""
    perceiver = e2e.Perceiver(CFG, MODEL)
    camera, lidar, action = _inputs(2, 6, seed=4)
    action = action * jnp.asarray([1.0, 0.3])  # steering commands within the world's limits
    start = jnp.asarray([[100.0, 200.0, 1.0, 0.0, 5.0], [300.0, 50.0, 0.0, 1.0, 8.0]], jnp.float32)
    step = jax.jit(perceiver.step, static_argnames="measure")
    grid = pose_belief.grid_of(CFG.model)
    odometry, measured, global_state = perceiver.init(2), perceiver.init(2), perceiver.init(2)
    for t in range(6):
        odometry, out = step(params, odometry, camera[:, t], lidar[:, t], action[:, t], start_pose=start, measure=False)
        want = np.stack([_odometry(np.asarray(start[b]), np.asarray(action[b, : t + 1]))[-1] for b in range(2)])
        np.testing.assert_allclose(out.pose, want, rtol=1e-5, atol=2e-4)
        measured, m_out = step(params, measured, camera[:, t], lidar[:, t], action[:, t], start_pose=start)
        if t == 0:
            cell = np.floor((np.asarray(start[:, :2]) - pose_belief.AREA_ORIGIN_M) / grid.cell_m).astype(int)
            for b in range(2):  # the start's bilinear cells only: the measurement cannot add mass elsewhere
                place = np.asarray(m_out.pose_place[b])
                near = place[max(cell[b, 1] - 1, 0) : cell[b, 1] + 2, max(cell[b, 0] - 1, 0) : cell[b, 0] + 2]
                np.testing.assert_allclose(near.sum(), 1.0, rtol=1e-5)
        global_state, global_out = step(params, global_state, camera[:, t], lidar[:, t], action[:, t])
        np.testing.assert_allclose(jnp.sum(global_out.pose_place, (1, 2)), 1.0, rtol=1e-5)
        assert global_out.pose_place.shape == (2, grid.n, grid.n)
    assert np.linalg.norm(np.asarray(out.pose[:, :2] - start[:, :2]), axis=-1).min() > 1.0  # it moved


@pytest.mark.slow
def test_pose_filter_none_reads_the_head_frame_by_frame(params):
    """Without the filter the pose is the frame's head decoded alone (mode + offset) and the belief is the
    head's own place x heading distribution, whatever came before."""
    cfg = config_lib.replace(CFG, model=dict(pose_filter="none"))
    perceiver, grid = e2e.Perceiver(cfg), pose_belief.grid_of(cfg.model)
    camera, lidar, action = _inputs(2, 3, seed=5)
    state = perceiver.init(2)
    latent_state = model_lib.init_filter_state(2, cfg)
    for t in range(3):
        state, out = jax.jit(perceiver.step)(params, state, camera[:, t], lidar[:, t], action[:, t])
        latent_state, latent = model_lib.filter_step(
            params, latent_state, camera[:, t], lidar[:, t], action[:, t], None, cfg
        )
        head = model_lib.pose_belief_head(params, latent, cfg)
        np.testing.assert_allclose(out.pose, pose_belief.decode(head, grid), rtol=1e-5, atol=1e-4)
        place = np.asarray(jax.nn.softmax(head["place_logit"], -1)).reshape(2, grid.n, grid.n)
        np.testing.assert_allclose(out.pose_place, place, rtol=1e-4, atol=1e-7)


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """(workdir, config, final train state) of a 2-step tiny run."""
    cfg = config_lib.replace(CFG, train=dict(num_steps=2, checkpoint_every=2, log_every=1))
    workdir = tmp_path_factory.mktemp("run")
    return workdir, cfg, train_lib.train(cfg, str(workdir))


@pytest.mark.slow
def test_load_returns_the_trained_params_and_boxes_decode(trained_run):
    tmp_path, cfg, trained = trained_run
    perceiver, params = e2e.load(str(tmp_path))
    assert perceiver.cfg == cfg
    # the run's motion model, fitted when training started: not the exact bicycle of a world without a plant
    assert perceiver.motion_model == MotionModel.load(str(tmp_path)) != MotionModel()
    assert 0.2 < perceiver.motion_model.lag_share < 0.8 and perceiver.motion_model.heading_noise_rad2pm > 0
    jax.tree.map(
        lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), params, jax.device_get(trained.params)
    )
    camera, lidar, action = _inputs(2, 1, seed=3)
    _, out = perceiver.step(params, perceiver.init(2), camera[:, 0], lidar[:, 0], action[:, 0])
    assert out.det_cls.shape == (2, R, R, 1) and out.pose.shape == (2, 5)


@pytest.mark.slow
def test_the_readmes_example_runs_as_written_on_a_trained_run(trained_run):
    """The README's inference example, run on a trained run with the inputs its comments describe (4 streams),
    gives the shapes its comments state: a user who copies it meets no renamed field."""
    workdir, cfg, _ = trained_run
    run_readme_example(workdir, cfg)


def test_boxes_recover_the_cars_behind_pixor_maps():
    """Maps made from known boxes: every positive pixel decodes to its car; NMS leaves one box per car."""
    perceiver = e2e.Perceiver(CFG)
    cars = np.array([[6.0, 4.0, 0.3, 4.6, 1.9], [-5.0, -6.0, -1.2, 5.5, 2.2]], np.float32)
    det_cls, det_reg = pixor.targets(jnp.asarray(cars), R)
    outputs = e2e.PerceiverOutputs(
        det_cls=jnp.stack([det_cls, jnp.zeros_like(det_cls)]),
        det_reg=jnp.stack([det_reg, det_reg]),
        pose=jnp.zeros((2, 5)),
    )
    (boxes, scores), (none, _) = perceiver.boxes(outputs)
    assert len(none) == 0
    assert len(boxes) == 2 and np.all(scores == 1.0)
    order = np.argsort(boxes[:, 0])[::-1]
    np.testing.assert_allclose(boxes[order], cars, atol=1e-4)


def test_load_imports_no_evaluation_world_or_cv2():
    """``e2e_percep_jax.load`` needs only the model and the checkpoint reader: in a fresh process, touching it
    imports neither cv2 nor the world, the town, the sensors or the evaluation."""
    script = (
        "import sys, e2e_percep_jax; e2e_percep_jax.load; "
        "print(' '.join(m for m in sys.modules if m.split('.')[0] in ('e2e_percep_jax', 'cv2')))"
    )
    env = dict(os.environ, PYTHONPATH=ROOT)
    loaded = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
    modules = loaded.stdout.split()
    assert "e2e_percep_jax.api" in modules, modules
    heavy = (
        "cv2",
        "e2e_percep_jax.sim.world",
        "e2e_percep_jax.sim.town",
        "e2e_percep_jax.sim.sensors",
        "e2e_percep_jax.evaluate",
    )
    assert not [m for m in modules if m in heavy or m.startswith("cv2.")], modules


def _in_top_mass(p, index, mass=0.95):
    """Whether entry ``index`` of probabilities p [M] is among the most probable entries that, sorted,
    first hold ``mass`` of the total (a brute-force sort)."""
    order = np.argsort(-p, kind="stable")
    return index in order[: np.searchsorted(np.cumsum(p[order]), mass * np.sum(p)) + 1]


@pytest.mark.slow
def test_filter_sweep_reports_the_regions_coverage_under_each_heading_noise(trained_run):
    """The filter sweep replays the run's heads through each setting (every combination of the listed
    values, at the one position asked for) and reports how often the truth lies in the belief's 95 %
    regions. Counted again here for the filter's defaults with the heading noise 10,000-fold: the sweep's
    drives perceived through ``Perceiver.step``, its motion model's heading noise scaled by 10,000 /
    ``HEADING_NOISE_SCALE``; the true cell and (heading bin, cell) indexed by hand, each region found by
    sorting the belief's probabilities. The sweep's place / joint shares, and the joint share in standing
    / moving frames, are these counts (78.3 % of the joint, so not all frames inside)."""
    workdir, _, _ = trained_run
    worlds, frames, seed, scale = 2, 30, 2000, 10000.0
    defaults = pose_belief.default_settings()
    sweep = os.path.join(ROOT, "experiments", "pose_filter_sweep.py")
    result = subprocess.run(
        [
            sys.executable,
            sweep,
            f"--workdir={workdir}",
            f"--eval_seed={seed}",
            f"--frames={frames}",
            f"--worlds={worlds}",
            f"--floors={defaults['floor']:g}",
            f"--powers={defaults['power']:g}",
            f"--speed_gains={defaults['speed_gain']:g}",
            f"--relocations={defaults['relocation']:g}",
            f"--heading_noise_scales=1,{scale:g}",
            f"--full_measure_distances=0,{defaults['full_measure_m']:g}",
            f"--stopped_shares={defaults['stopped_share']:g}",
            "--positions=local_mean",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    lines = result.stdout.splitlines()
    rows = [line for line in lines if "heading_noise_scale" in line]
    assert len(rows) == 4 and all("local_mean" in row for row in rows), result.stdout
    header = [c.strip() for c in next(line for line in lines if line.startswith("| filter")).split("|")]
    column = header.index("truth in 95 % region: place / + heading")
    (split_column,) = [i for i, c in enumerate(header) if c.startswith("+ heading in standing / moving frames (")]
    shares = lambda row, i: tuple(map(float, row.split("|")[i].strip(" %").split(" / ")))
    coverage = [shares(row, column) for row in rows]
    assert coverage[0][1] != coverage[2][1], coverage  # heading noise x1 against x10000, measurements in full
    name = ", ".join(f"{k} {v:g}" for k, v in (defaults | {"heading_noise_scale": scale}).items()) + ", local_mean"
    (recounted,) = [row for row in rows if row.split("|")[1].strip() == name]

    # The same drives as the sweep's: its seed, warm-up and frames.
    perceiver, params = e2e.load(str(workdir))
    cfg, grid = perceiver.cfg, pose_belief.grid_of(perceiver.cfg.model)
    town = town_lib.build_town(cfg.world.town_seed)
    drive_cfg = config_lib.replace(cfg, data=dict(batch_size=worlds))
    states = jax.jit(batch_lib.warm_up, static_argnames="cfg")(jax.random.PRNGKey(seed), town, drive_cfg)
    _, drive = jax.jit(jax.vmap(lambda s: rollout.drive(s, town, frames, cfg.data.image_size)))(states)
    camera, lidar, action = (np.asarray(drive[k]) for k in ("camera", "lidar", "action"))
    prev_action = np.concatenate([np.zeros_like(action[:, :1]), action[:, :-1]], 1)
    truth = np.asarray(drive["pose"], np.float64)  # [W, T, 5]
    model = perceiver.motion_model
    noisy = dataclasses.replace(
        perceiver,
        motion_model=dataclasses.replace(
            model, heading_noise_rad2pm=model.heading_noise_rad2pm * scale / pose_belief.HEADING_NOISE_SCALE
        ),
    )
    step, state = jax.jit(noisy.step), noisy.init(worlds)
    n, h = grid.n, grid.heading_bins
    inside = np.zeros((frames, worlds, 2), bool)  # (place, joint)
    for t in range(frames):
        state, _ = step(params, state, camera[:, t], lidar[:, t], prev_action[:, t])
        belief = np.asarray(state.pose.belief, np.float64).reshape(worlds, h, n * n)
        for w in range(worlds):
            j, i = ((truth[w, t, :2] - pose_belief.AREA_ORIGIN_M) // grid.cell_m).astype(int)
            cell = i * n + j  # row i along y, column j along x, row-major
            # bin k: headings [-pi + k bin, -pi + (k + 1) bin) plus the belief's heading offset
            yaw = np.arctan2(truth[w, t, 3], truth[w, t, 2]) - float(state.pose.yaw_offset_rad[w])
            k = int(((yaw + np.pi) % (2 * np.pi)) // grid.bin_rad) % h
            inside[t, w] = _in_top_mass(belief[w].sum(0), cell), _in_top_mass(belief[w].ravel(), k * n * n + cell)
    standing = truth[..., 4].T < 0.5  # [T, W]: the sweep's standing car, under 0.5 m/s
    assert f"({100 * standing.mean():.0f} % stand)" in header[split_column], header[split_column]
    assert 0 < inside[..., 1].mean() < 1, inside.mean((0, 1))
    percent = lambda x: float(f"{100 * x.mean():.1f}")
    split = inside[..., 1][standing], inside[..., 1][~standing]
    want = (percent(inside[..., 0]), percent(inside[..., 1])), tuple(map(percent, split))
    assert (shares(recounted, column), shares(recounted, split_column)) == want, (recounted, want)
