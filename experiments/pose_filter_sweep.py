"""Chooses the pose belief filter's settings on drives the evaluation never uses, for a trained run.

    python experiments/pose_filter_sweep.py --workdir=runs/cpu --eval_seed=2000 --frames=500 \
        --floors=0.01,0.05,0.2 --powers=0.25,0.5,1 --speed_gains=0.2

E = ``--worlds`` drives of the run's town start from ``PRNGKey(--eval_seed)`` (the evaluation's own seed,
1000, is held out from this choice), warm their traffic up and drive ``--frames`` frames each. The model
filters its latent along each drive once; then the histogram filter (``pose_belief.filter_step``) runs over
the same head outputs for every combination of measurement floor, measurement power, speed gain,
relocation share, factor on the motion model's heading process noise, distance of a frame's full
measurement and standing car's share of it, each with the ``--positions``
ways of reading a position off the belief (default: all of ``pose_belief.POSITIONS``), and the location /
heading errors (mean, median, over every frame, and over frames 100 on) and how often the truth lies in the
belief's 95 % region are printed as a table.
"""

import functools
import itertools
import sys

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

from e2e_percep_jax import checkpoint, launch, metrics, pose_belief
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax.sim import batch as batch_lib
from e2e_percep_jax.sim import rollout
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim.motion import MotionModel

flags.DEFINE_string("workdir", None, "a training run with the belief pose head")
flags.DEFINE_integer("step", None, "checkpoint (default: the latest)")
flags.DEFINE_integer("eval_seed", 2000, "drives' start keys; not the evaluation's 1000")
flags.DEFINE_integer("worlds", 8, "drives")
flags.DEFINE_integer("frames", 500, "frames per drive")
flags.DEFINE_list("floors", ["0.01", "0.05", "0.2"], "measurement floors to try")
flags.DEFINE_list("powers", ["0.125", "0.25", "0.5"], "measurement powers to try")
flags.DEFINE_list("speed_gains", ["0.2"], "speed gains to try")
flags.DEFINE_list(
    "relocations", ["0.001"], "shares of each cell's mass spread over all headings after each motion step, to try"
)
flags.DEFINE_list(
    "heading_noise_scales",
    [f"{pose_belief.HEADING_NOISE_SCALE:g}"],
    "factors on the calibrated motion model's heading process noise, to try",
)
flags.DEFINE_list(
    "full_measure_distances",
    [f"{pose_belief.FULL_MEASURE_M:g}"],
    "distances (m) driven in a frame from which its measurement counts in full (0: always in full), to try",
)
flags.DEFINE_list(
    "stopped_shares",
    [f"{pose_belief.STOPPED_SHARE:g}"],
    "shares of a full measurement that a standing car's frame counts, to try",
)
flags.DEFINE_list(
    "positions", list(pose_belief.POSITIONS), f"ways of reading the position, any of {pose_belief.POSITIONS}"
)
FLAGS = flags.FLAGS
STANDING_MPS = 0.5  # a frame whose true speed is under this counts as the car standing


def main(argv):
    try:
        launch.prepare(argv)
        names = tuple(pose_belief.default_settings())  # filter_step's keywords, in the order of the flags below
        values = itertools.product(
            FLAGS.floors,
            FLAGS.powers,
            FLAGS.speed_gains,
            FLAGS.relocations,
            FLAGS.heading_noise_scales,
            FLAGS.full_measure_distances,
            FLAGS.stopped_shares,
        )
        settings = [dict(zip(names, map(float, v), strict=True)) for v in values]
        for position in FLAGS.positions:
            if position not in pose_belief.POSITIONS:
                raise ValueError(f"--positions: {position!r} is not one of {pose_belief.POSITIONS}")
        settings = [(setting, position) for setting in settings for position in FLAGS.positions]
        if any(float(d) < 0 for d in FLAGS.full_measure_distances):
            raise ValueError(f"--full_measure_distances={','.join(FLAGS.full_measure_distances)}: must be >= 0")
        if any(not 0 <= float(s) <= 1 for s in FLAGS.stopped_shares):
            raise ValueError(f"--stopped_shares={','.join(FLAGS.stopped_shares)}: each must lie in [0, 1]")
        if FLAGS.worlds < 1 or FLAGS.frames < 1:
            raise ValueError("--worlds and --frames must be positive")
        cfg, params, step = checkpoint.restore_params(FLAGS.workdir, step=FLAGS.step)
        if cfg.model.pose_head != "belief":
            raise ValueError(f"--workdir={FLAGS.workdir}: its pose head is {cfg.model.pose_head!r}, not the belief")
        motion_model = MotionModel.load(FLAGS.workdir)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"error: {e}")
    grid = pose_belief.grid_of(cfg.model)
    town = town_lib.build_town(cfg.world.town_seed)
    drive_cfg = config_lib.replace(cfg, data=dict(batch_size=FLAGS.worlds))
    warm_up = jax.jit(batch_lib.warm_up, static_argnames="cfg")  # (one program, not the reset op by op)
    states = warm_up(jax.random.PRNGKey(FLAGS.eval_seed), town, drive_cfg)
    _, frames = jax.jit(jax.vmap(lambda s: rollout.drive(s, town, FLAGS.frames, cfg.data.image_size)))(states)
    time_major = lambda x: jnp.swapaxes(x, 0, 1)
    prev_action = jnp.concatenate([jnp.zeros_like(frames["action"][:, :1]), frames["action"][:, :-1]], 1)

    @jax.jit
    def heads(params):
        def body(state, xs):
            camera, lidar, action = xs
            state, latent = model_lib.filter_step(params, state, camera, lidar, action, None, cfg)
            return state, model_lib.pose_belief_head(params, latent, cfg)

        xs = tuple(map(time_major, (frames["camera"], frames["lidar"], prev_action)))
        return jax.lax.scan(body, model_lib.init_filter_state(FLAGS.worlds, cfg), xs)[1]

    head = heads(params)  # [T, E, ...]
    first = jnp.arange(FLAGS.frames) == 0

    @functools.partial(jax.jit, static_argnames="position")
    def track(setting, position):
        def body(state, xs):
            h, action, is_first, pose = xs
            state, estimate = pose_belief.filter_step(
                state, h, action, jnp.full(FLAGS.worlds, is_first), grid, motion_model, position=position, **setting
            )
            return state, (estimate, pose_belief.region_share(state, pose, grid))

        xs = (head, time_major(prev_action), first, time_major(frames["pose"]))
        return jax.lax.scan(body, pose_belief.init_state(FLAGS.worlds, grid), xs)[1]

    truth = np.asarray(time_major(frames["pose"]))
    standing = truth[..., 4] < STANDING_MPS
    no_region = np.full(truth.shape[:2] + (2,), np.nan)
    rows = [("head alone (no filter)", (np.asarray(pose_belief.decode(head, grid)), no_region))]
    rows += [
        (
            ", ".join(f"{name} {value:g}" for name, value in setting.items()) + f", {position}",
            jax.tree.map(np.asarray, track(setting, position=position)),
        )
        for setting, position in settings
    ]
    print(f"{FLAGS.workdir} step {step}: {FLAGS.worlds} drives x {FLAGS.frames} frames from PRNGKey({FLAGS.eval_seed})")
    print(
        "| filter | location mean / median (m) | from frame 100: mean / median (m) | heading mean (rad) | "
        "within 10 m | drives ending within 10 m | truth in 95 % region: place / + heading | "
        f"+ heading in standing / moving frames ({100 * standing.mean():.0f} % stand) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, (pred, inside) in rows:
        err = metrics.pose_errors(pred, truth)
        late = err.location_m[100:]
        place, joint = 100 * inside.reshape(-1, 2).mean(0)
        joint_standing, joint_moving = (100 * inside[..., 1][m].mean() for m in (standing, ~standing))
        print(
            f"| {name} | {err.location_m.mean():.1f} / {np.median(err.location_m):.1f} | "
            f"{late.mean():.1f} / {np.median(late):.1f} | {err.heading_rad.mean():.3f} | "
            f"{100 * np.mean(err.location_m <= 10):.1f} % | {np.sum(err.location_m[-1] <= 10)} / {FLAGS.worlds} | "
            f"{place:.1f} / {joint:.1f} % | {joint_standing:.1f} / {joint_moving:.1f} % |",
            flush=True,
        )


if __name__ == "__main__":
    flags.mark_flag_as_required("workdir")
    app.run(main)
