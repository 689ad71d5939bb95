"""The public inference API: batching, streaming vs the training-time scan, jit/scan inside user code,
and loading a trained run. (Bad arguments and damaged runs are rows of test_bad_input.py.)"""
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import e2e_percep_jax as e2e
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax import pixor, pose_belief
from e2e_percep_jax import train as train_lib

CFG = config_lib.get_config("tiny")
R = CFG.data.image_size
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


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
        state, out = step(params, state, camera[:, t], lidar[:, t], prev_action[:, t],
                          None if keys is None else keys[t])
        outs.append(out)
    return jax.tree.map(lambda *x: jnp.stack(x, 1), *outs)


@pytest.mark.slow
def test_batch_of_streams_equals_each_stream_alone(params):
    perceiver = e2e.Perceiver(CFG)
    camera, lidar, action = _inputs(3, 4)
    together = _stream(perceiver, params, camera, lidar, action)
    for i in range(3):
        alone = _stream(perceiver, params, camera[i:i + 1], lidar[i:i + 1], action[i:i + 1])
        for k in ("det_cls", "det_reg", "pose", "z", "roadmap"):
            np.testing.assert_allclose(together[k][i:i + 1], alone[k], rtol=1e-5, atol=1e-5, err_msg=k)


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
    np.testing.assert_allclose(streamed["z"], z, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_step_inside_a_users_jit_and_scan(params):
    perceiver = e2e.Perceiver(CFG)
    camera, lidar, action = _inputs(2, 3, seed=2)

    @jax.jit
    def user_rollout(params, camera, lidar, action):
        def body(state, xs):
            state, out = perceiver.step(params, state, *xs)
            return state, out["pose"]
        xs = tuple(jnp.swapaxes(x, 0, 1) for x in (camera, lidar, action))
        return jax.lax.scan(body, perceiver.init(camera.shape[0]), xs)[1]

    poses = jnp.swapaxes(user_rollout(params, camera, lidar, action), 0, 1)
    streamed = _stream(perceiver, params, camera, lidar, action)
    np.testing.assert_allclose(poses, streamed["pose"], rtol=1e-5, atol=1e-4)
    assert poses.shape == (2, 3, 5)


@pytest.mark.slow
def test_pose_belief_through_the_api_known_start_and_global(params):
    """The belief head's outputs: ``pose_place`` is a distribution over the cells; with ``start_pose`` the
    pose is the known start on a stream's first frame, then that start moved by the actions alone (the
    filter's bicycle model, the same as ``pose_belief``'s), whatever the images."""
    perceiver = e2e.Perceiver(CFG)
    camera, lidar, action = _inputs(2, 4, seed=4)
    start = jnp.asarray([[100.0, 200.0, 1.0, 0.0, 5.0], [300.0, 50.0, 0.0, 1.0, 8.0]], jnp.float32)
    step = jax.jit(perceiver.step)
    state, global_state = perceiver.init(2), perceiver.init(2)
    grid = pose_belief.grid_of(CFG.model)
    track = pose_belief.init_state(2, grid)
    for t in range(4):
        state, out = step(params, state, camera[:, t], lidar[:, t], action[:, t], start_pose=start)
        track, want = pose_belief.filter_step(track, None, action[:, t], jnp.asarray([t == 0] * 2), grid,
                                              start_pose=start)
        np.testing.assert_allclose(out["pose"], want, rtol=1e-6, atol=1e-4)
        if t == 0:
            np.testing.assert_allclose(out["pose"], start, atol=1e-4)
        global_state, global_out = step(params, global_state, camera[:, t], lidar[:, t], action[:, t])
        np.testing.assert_allclose(jnp.sum(global_out["pose_place"], (1, 2)), 1.0, rtol=1e-5)
        assert global_out["pose_place"].shape == (2, grid.n, grid.n)
    assert not np.allclose(out["pose"][:, :2], start[:, :2])  # it moved


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
        latent_state, latent = model_lib.filter_step(params, latent_state, camera[:, t], lidar[:, t], action[:, t],
                                                     None, cfg)
        head = model_lib.pose_belief_head(params, latent, cfg)
        np.testing.assert_allclose(out["pose"], pose_belief.decode(head, grid), rtol=1e-5, atol=1e-4)
        place = np.asarray(jax.nn.softmax(head["place_logit"], -1)).reshape(2, grid.n, grid.n)
        np.testing.assert_allclose(out["pose_place"], place, rtol=1e-4, atol=1e-7)


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
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)),
                 params, jax.device_get(trained.params))
    camera, lidar, action = _inputs(2, 1, seed=3)
    _, out = perceiver.step(params, perceiver.init(2), camera[:, 0], lidar[:, 0], action[:, 0])
    assert out["det_cls"].shape == (2, R, R, 1) and out["pose"].shape == (2, 5)


def test_boxes_recover_the_cars_behind_pixor_maps():
    """Maps made from known boxes: every positive pixel decodes to its car; NMS leaves one box per car."""
    perceiver = e2e.Perceiver(CFG)
    cars = np.array([[6.0, 4.0, 0.3, 4.6, 1.9], [-5.0, -6.0, -1.2, 5.5, 2.2]], np.float32)
    det_cls, det_reg = pixor.targets(jnp.asarray(cars), R)
    outputs = {"det_cls": jnp.stack([det_cls, jnp.zeros_like(det_cls)]), "det_reg": jnp.stack([det_reg, det_reg])}
    (boxes, scores), (none, _) = perceiver.boxes(outputs)
    assert len(none) == 0
    assert len(boxes) == 2 and np.all(scores == 1.0)
    order = np.argsort(boxes[:, 0])[::-1]
    np.testing.assert_allclose(boxes[order], cars, atol=1e-4)


def test_load_imports_no_evaluation_world_or_cv2():
    """``e2e_percep_jax.load`` needs only the model and the checkpoint reader: in a fresh process, touching it
    imports neither cv2 nor the world, the town, the sensors or the evaluation."""
    script = ("import sys, e2e_percep_jax; e2e_percep_jax.load; "
              "print(' '.join(m for m in sys.modules if m.split('.')[0] in ('e2e_percep_jax', 'cv2')))")
    env = dict(os.environ, PYTHONPATH=ROOT)
    loaded = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
    modules = loaded.stdout.split()
    assert "e2e_percep_jax.api" in modules, modules
    heavy = ("cv2", "e2e_percep_jax.world", "e2e_percep_jax.town", "e2e_percep_jax.sensors", "e2e_percep_jax.evaluate")
    assert not [m for m in modules if m in heavy or m.startswith("cv2.")], modules
