"""The bird-eye latent's ego-motion head against the world's true motion, on drives of any town.

    python experiments/motion_head_error.py --workdir=runs/cpu-bev --town_seed=7

A run trained with ``--model.latent=bev`` predicts, each frame, how the ego moved since the last one (dx, dy m
in the last frame's axes, dyaw rad; ``model.filter_step``'s ``motion``), from the frame's features, the last
latent and the commands; the grid is warped by it. This drives ``--drives`` worlds of town ``--town_seed``
(reset from ``--seed``, after the config's warm-up) for ``--frames`` frames, filters each with the run's
latent filter (posterior means, one scan), and prints as JSON: the head's error per step against the true
motion between consecutive poses (RMS and median absolute, per component), and the drift of the path that
its motions integrate from each drive's true first pose, per 100 m driven (the odometries' figure:
``metrics``' ``drift_per_100m``), beside the distance driven. A ``--world.*`` flag changes the car driven.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

from e2e_percep_jax import bev_latent, checkpoint, launch
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import rollout, world
from e2e_percep_jax.sim import town as town_lib

flags.DEFINE_string("workdir", None, "a training run with the bird-eye latent")
flags.DEFINE_integer("town_seed", 7, "the town driven")
flags.DEFINE_integer("seed", 1000, "the worlds' reset key")
flags.DEFINE_integer("drives", 8, "drives (worlds)")
flags.DEFINE_integer("frames", 600, "frames driven")
FLAGS = flags.FLAGS


def integrate(start_pose, motion):
    """Poses [T+1, 3] (x m, y m, yaw rad) from ``start_pose`` [5] and per-step motions [T, 3] in the earlier
    frame's axes (:func:`bev_latent.relative_motion`'s inverse, chained)."""

    def step(pose, m):
        x, y, yaw = pose
        dx, dy = geo.rotate(m[:2], yaw)
        after = jnp.stack([x + dx, y + dy, yaw + m[2]])
        return after, after

    first = jnp.stack([start_pose[0], start_pose[1], geo.pose_yaw(start_pose)])
    return jnp.concatenate([first[None], jax.lax.scan(step, first, motion)[1]])


def main(argv):
    cfg = launch.run_config(argv, FLAGS.workdir)
    if cfg.model.latent != "bev":
        raise app.UsageError(f"--workdir={FLAGS.workdir}: trained with --model.latent={cfg.model.latent}; needs bev")
    if FLAGS.drives < 1 or FLAGS.frames < 2:
        raise app.UsageError("--drives must be >= 1 and --frames >= 2")
    _, params, _ = checkpoint.restore_params(FLAGS.workdir, cfg)
    town = town_lib.build_town(FLAGS.town_seed)

    @jax.jit
    def record(key):
        state = rollout.advance(world.reset(key, town, cfg.world), town, cfg.data.warmup_steps)
        return rollout.drive(state, town, FLAGS.frames, cfg.data.image_size)[1]

    frames = jax.vmap(record)(jax.random.split(jax.random.PRNGKey(FLAGS.seed), FLAGS.drives))
    filtered = jax.jit(lambda c, li, a: model_lib.filter_sequence(params, c, li, a, None, cfg))
    predicted = np.asarray(filtered(frames.camera, frames.lidar, frames.action)["motion"][:, 1:], np.float64)
    truth = np.asarray(bev_latent.relative_motion(frames.pose[:, :-1], frames.pose[:, 1:]), np.float64)
    error = predicted - truth  # [W, T, 3]
    path = np.asarray(jax.vmap(integrate)(frames.pose[:, 0], jnp.asarray(predicted, jnp.float32)))
    pose = np.asarray(frames.pose, np.float64)
    end_error = np.linalg.norm(path[:, -1, :2] - pose[:, -1, :2], axis=-1)
    distance = np.sum(np.linalg.norm(np.diff(pose[..., :2], axis=1), axis=-1), axis=1)
    names = ("dx_m", "dy_m", "dyaw_rad")
    result = {
        "town_seed": FLAGS.town_seed,
        "drives": FLAGS.drives,
        "frames": FLAGS.frames,
        "step_error_rms": {n: float(np.sqrt(np.mean(error[..., i] ** 2))) for i, n in enumerate(names)},
        "step_error_median_abs": {n: float(np.median(np.abs(error[..., i]))) for i, n in enumerate(names)},
        "true_step_rms": {n: float(np.sqrt(np.mean(truth[..., i] ** 2))) for i, n in enumerate(names)},
        "drift_per_100m": float(100.0 * end_error.sum() / max(distance.sum(), 1e-9)),
        "end_error_m": [round(float(v), 2) for v in end_error],
        "distance_m": [round(float(v), 1) for v in distance],
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    flags.mark_flag_as_required("workdir")
    app.run(main, flags_parser=config_lib.parse_flags)
