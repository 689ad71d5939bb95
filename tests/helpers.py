"""What more than one test module uses: the tiny config and its synthetic frames, the jitted loss and
gradients, NumPy forms of the loss terms, lidar scans of hand-built streets, and the training launcher with
the files a run writes.

A plain module, not conftest.py: the tests import these names directly (``from helpers import ...``), and so
does code that the training tests run in a fresh ``python -c`` subprocess, which imports no pytest plugin.
``pythonpath = ["tests"]`` in pyproject.toml puts this folder on ``sys.path``, whatever the import mode.
Fixtures shared by test modules belong in conftest.py.
"""

import functools
import importlib.util
import json
import os
import socket
import sys

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import config, loss, pose_belief
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import motion, sensors
from e2e_percep_jax.sim.motion import MotionModel

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the repository
TINY = config.get_config("tiny")
EXACT_PLANT = {name: 0.0 for name in config.PLANT_FIELDS}  # the world's ego plant off: the exact-action world


OPTIMISATION_FLAG = "--xla_backend_optimization_level"  # lowered for the suite by conftest.py
# XLA's default optimisation (level 3) for one program, ``jax.jit(f, compiler_options=OPTIMISED)``: for the
# few a test runs long (a filter over thousands of frames), which run 3-5 times slower unoptimised.
OPTIMISED = {OPTIMISATION_FLAG.lstrip("-"): 3}


def environment():
    """A copy of this process's environment for the subprocesses that worker threads start. Take it in the
    main thread and hand it to them: pytest sets and removes PYTEST_CURRENT_TEST there as tests run, so a
    copy taken key by key in another thread can meet a key that has just gone (a KeyError)."""
    return dict(os.environ)


def xla_flags(*extra, env=os.environ):
    """The suite's XLA_FLAGS (its optimisation level kept) as ``env`` has them, and ``extra``, for a
    subprocess's environment."""
    return " ".join([env.get("XLA_FLAGS", ""), *extra]).strip()


def default_optimisation_env():
    """This process's environment with XLA's backend optimisation at its default level, for a subprocess
    whose numbers must equal ones recorded outside the suite."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith(OPTIMISATION_FLAG)]
    return dict(os.environ, XLA_FLAGS=" ".join(flags))


@functools.cache
def load_experiment(name):
    """The script ``experiments/<name>.py`` as a module (experiments/ is not a package), loaded once: a
    script defines its absl flags when loaded, and a second definition would be an error."""
    spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, "experiments", f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ----------------------------------------------------------------------------- frames, loss and its terms


def odometry_model(**fields):
    """The exact bicycle with the lidar odometry's priors and noises set (every scan correction on), and
    ``fields`` changed."""
    odometry = dict(yaw_bias_std_1pm=0.004, yaw_gain_std=0.03, yaw_noise_rad2pm=1e-7, scan_heading_noise_rad=0.002)
    odometry.update(speed_gain_std=0.03, speed_noise_mps=0.002, scan_distance_noise=0.25)
    return MotionModel(**{**odometry, **fields})


# ----------------------------------------------------------------------------- lidar scans of hand-built streets


def buildings(centres_m, rng):
    """Obstacles: boxes of 3-8 m sides and random yaw at town points ``centres_m`` [M, 2]."""
    m = len(centres_m)
    box = np.column_stack([centres_m, rng.uniform(-np.pi, np.pi, m), rng.uniform(3, 8, (m, 2))]).astype(np.float32)
    return box


@jax.jit  # one program per shape: op by op, a scan's hundreds of small programs cost more than they run
def lidar_scan(box_town, pose, height_m=None):
    """The lidar scan of buildings ``box_town`` [M, 5] (the nearest SCAN_BUILDINGS of them, as the sensors
    cull; 6 m tall, or ``height_m`` [M]) from ego pose (x, y, yaw)."""
    box = geo.box_to_ego(jnp.asarray(box_town), jnp.asarray(pose[:2], jnp.float32), jnp.float32(pose[2]))
    height_m = jnp.full((box.shape[0],), 6.0) if height_m is None else jnp.asarray(height_m, jnp.float32)
    m = min(box.shape[0], sensors.SCAN_BUILDINGS)
    nearest = jnp.argsort(jnp.linalg.norm(box[:, :2], axis=-1))[:m]
    obstacles = sensors.Obstacles(
        box=box[nearest],
        height_m=height_m[nearest],
        color=jnp.zeros((m, 3)),
        is_vehicle=jnp.zeros((m,), bool),
        valid=jnp.ones((m,), bool),
        vehicle_index=jnp.full((m,), -1, jnp.int32),
    )
    return sensors.render_scan(obstacles)


def street(ds, dyaw):
    """A drive's true path from its steps ``ds`` [T] m and yaw changes ``dyaw`` [T] rad (from the origin,
    heading along x), down a street of buildings that follow it (one each side every 6-9 m): the path's
    (x, y) [T + 1, 2] and yaw [T + 1], and its lidar scans [T + 1, SCAN_AZIMUTHS]."""
    yaw = np.concatenate([[0.0], np.cumsum(dyaw)])
    steps = np.asarray(motion.centre_move(jnp.asarray(ds), jnp.asarray(dyaw), jnp.asarray(yaw[:-1, None])))[:, 0]
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, 0)])
    rng = np.random.default_rng(2)
    side = np.stack([-np.sin(yaw), np.cos(yaw)], -1)
    along = np.arange(0, len(yaw), 9)
    centres = np.concatenate([xy[along] + 10 * side[along], xy[along] - 11 * side[along]])
    box = buildings(centres + rng.normal(0, 1.0, centres.shape), rng)
    return xy, yaw, jax.vmap(lidar_scan, in_axes=(None, 0))(box, jnp.asarray(np.column_stack([xy, yaw]), jnp.float32))


def frame_contract(image_size, num_boxes):
    """One observed frame's keys and their (dtype, shape): the frame contract, less what ``rollout.drive``
    adds: the ``action`` (it needs the next state) and ``boxes_frames_since_seen`` (it needs the earlier
    frames)."""
    r, n = image_size, num_boxes
    return {
        "camera": (np.uint8, (r, r, 3)),
        "lidar": (np.uint8, (r, r, 3)),
        "lidar_scan": (np.float32, (360,)),
        "roadmap": (np.uint8, (r, r, 3)),
        "det_cls": (np.float32, (r, r, 1)),
        "det_reg": (np.float32, (r, r, 6)),
        "pose": (np.float32, (5,)),
        "boxes": (np.float32, (n, 5)),
        "boxes_valid": (np.bool_, (n,)),
        "boxes_lidar_visible": (np.bool_, (n,)),
        "boxes_camera_visible": (np.bool_, (n,)),
    }


def synthetic_batch(seed, cfg, batch_size=None):
    """Random frames (NumPy, no compile) with the frame contract's keys, dtypes and shapes [B, T+1, ...]."""
    b, t1, r = batch_size or cfg.data.batch_size, cfg.data.seq_len + 1, cfg.data.image_size
    rng = np.random.default_rng(seed)
    image = lambda: rng.integers(0, 256, (b, t1, r, r, 3), np.uint8)
    heading = rng.uniform(0, 2 * np.pi, (b, t1))
    pose = np.stack(
        [
            rng.uniform(0, 400, (b, t1)),
            rng.uniform(0, 400, (b, t1)),
            np.cos(heading),
            np.sin(heading),
            rng.uniform(0, 12, (b, t1)),
        ],
        -1,
    )
    det_cls = (rng.uniform(size=(b, t1, r, r, 1)) > 0.9).astype(np.float32)
    # Regression targets exist at positive pixels only; elsewhere anything, here NaN / inf as a worst case.
    det_reg = np.where(det_cls > 0.5, rng.normal(size=(b, t1, r, r, 6)), rng.choice([np.nan, np.inf], (b, t1, r, r, 6)))
    return {
        "camera": image(),
        "lidar": image(),
        "roadmap": image(),
        "det_cls": det_cls,
        "det_reg": det_reg.astype(np.float32),
        "pose": pose.astype(np.float32),
        "action": rng.uniform(-0.3, 0.3, (b, t1, 2)).astype(np.float32),
    }


@functools.partial(jax.jit, static_argnames="cfg")
def loss_and_grads(params, batch, key, cfg):
    """((total, metrics), gradients) of the loss; one jitted object shared by the loss and training tests."""
    return jax.value_and_grad(loss.loss_fn, has_aux=True)(params, batch, key, cfg)


def np_focal(logit, y):
    """The torch peer's focal loss (on clamped probabilities), elementwise."""
    p = np.clip(1 / (1 + np.exp(-logit)), 1e-6, 1 - 1e-6)
    pt, a = np.where(y > 0.5, p, 1 - p), np.where(y > 0.5, 0.25, 0.75)
    return -a * (1 - pt) ** 2 * np.log(pt)


def np_smooth_l1(d):
    return np.where(np.abs(d) < 1, 0.5 * d**2, np.abs(d) - 0.5)


# ----------------------------------------------------------------------------- training runs and their files


LAUNCHER = [sys.executable, os.path.join(ROOT, "experiments", "train.py")]


def tiny(**train_fields):
    # learning rate 1e-3 for every run, so that the world run's KL is past its rise within a few hundred
    # steps (at initialisation q and p are alike, the KL is small; it peaks once the posterior encodes
    # the frames); 100 vehicles so the 32 m view often holds one (det_reg is non-zero only then).
    return config.replace(
        TINY,
        world=dict(num_vehicles=100),
        train=dict(dict(learning_rate=1e-3, max_nonfinite_in_a_row=3), **train_fields),
    )


# The same run from the launcher: flags on top of --config=tiny.
TINY_FLAGS = [
    "--config=tiny",
    "--world.num_vehicles=100",
    "--train.learning_rate=1e-3",
    "--train.max_nonfinite_in_a_row=3",
]


def np_region_share(p, mass):
    """By levels: how much of each state lies in the region holding exactly ``mass``. The states' distinct
    probabilities from the highest down; a level is wholly in while the levels above it and it hold at most
    ``mass`` of the total, wholly out once those above hold it all, and the level that crosses holds the
    rest in proportion to its states' mass. float [S]."""
    p = np.asarray(p, np.float64)
    levels, level_of = np.unique(p, return_inverse=True)
    level_mass = np.bincount(level_of.ravel(), p.ravel())[::-1]  # highest level first
    above = np.cumsum(level_mass) - level_mass
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(level_mass > 0, np.clip((mass * p.sum() - above) / level_mass, 0.0, 1.0), 0.0)
    return share[::-1][level_of.ravel()]


def np_kl(q_loc, q_scale, p_loc, p_scale):
    """KL(N(q) || N(p)) of diagonal Gaussians, per dimension, in closed form (NumPy)."""
    return np.log(p_scale / q_scale) + (q_scale**2 + (q_loc - p_loc) ** 2) / (2 * p_scale**2) - 0.5


def readme_section(heading):
    """The README's ``## heading`` section, up to the next ``## `` heading."""
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        text = f.read()
    start = text.index(f"\n## {heading}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end > 0 else len(text)]


def run_readme_example(workdir, cfg):
    """Runs the Python block of the README's "Inference API" section as written on the run in ``workdir``
    (trained with ``cfg``), with the inputs its comments describe (4 streams); checks the shapes its comments
    state and returns the names it left."""
    block = readme_section("Inference API").split("```python\n", 1)[1]
    example = block[: block.index("```\n")]
    assert example.count('"runs/demo"') == 1, example
    rng, r = np.random.default_rng(0), cfg.data.image_size
    names = {
        "camera": rng.integers(0, 256, (4, r, r, 3), np.uint8),
        "lidar": rng.integers(0, 256, (4, r, r, 3), np.uint8),
        "action": rng.uniform([-1.0, -0.3], [1.0, 0.3], (4, 2)).astype(np.float32),
        "start_pose": np.tile(np.float32([10.0, -5.0, 1.0, 0.0, 3.0]), (4, 1)),
        "lidar_scan": rng.uniform(0.0, 50.0, (4, 360)).astype(np.float32),
    }
    exec(example.replace('"runs/demo"', repr(str(workdir))), names)
    out, state, grid = names["out"], names["state"], pose_belief.grid_of(cfg.model)
    assert out.pose.shape == (4, 5) and out.pose_place.shape == (4, grid.n, grid.n)
    assert out.det_cls.shape == (4, r, r, 1) and out.det_reg.shape == (4, r, r, 6) and out.roadmap.shape == (4, r, r, 3)
    assert state.pose.belief.shape == (4, grid.heading_bins, grid.n, grid.n)
    boxes = names["boxes"]
    assert len(boxes) == 4 and all(b.shape[1:] == (5,) and s.shape == b.shape[:1] for b, s in boxes)
    # the known start without the measurement: stream 0, restarted, stands where its start_pose put it
    np.testing.assert_allclose(out.pose[0, :2], names["start_pose"][0, :2], atol=grid.cell_m)
    return names


def read_jsonl(path):
    with open(path) as f:
        return [json.loads(line) for line in f]


def checkpoint_steps(workdir):
    """Finished checkpoints (orbax writes into a temporary name and renames it to the step when done)."""
    path = os.path.join(workdir, "checkpoints")
    return sorted(int(d) for d in os.listdir(path) if d.isdigit()) if os.path.isdir(path) else []


def free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]
