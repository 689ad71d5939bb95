"""How many world steps until the traffic is steady: the statistic behind ``--data.warmup_steps``.

    python experiments/warmup_stats.py --config=cpu [--world.num_vehicles=100 --num_worlds=96]

Resets ``--num_worlds`` worlds of the config's town and drives them ``--max_steps`` steps, printing
every ``--every`` steps the mean speed and the stopped fraction (< 0.5 m/s) of the NPCs and of the
ego. A fresh reset spawns vehicles on evenly spaced slots at random safe speeds; queues at lights and
junctions form over the first light cycle, and a batch should be recorded only once these figures
have levelled off.
"""

import sys

import jax
import numpy as np
from absl import app, flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax.sim import rollout, world
from e2e_percep_jax.sim.town import build_town

config_lib.define_flags()
flags.DEFINE_integer("num_worlds", 96, "worlds averaged over")
flags.DEFINE_integer("max_steps", 800, "world steps driven")
flags.DEFINE_integer("every", 50, "print every this many steps")
flags.DEFINE_integer("seed", 0, "reset key")
FLAGS = flags.FLAGS

STOPPED_MPS = 0.5


def main(argv):
    try:
        config_lib.check_launch(argv, required=())
        cfg = config_lib.from_flags()
        for name in ("num_worlds", "max_steps", "every"):
            if FLAGS[name].value < 1:
                raise ValueError(f"--{name}={FLAGS[name].value}: must be >= 1")
    except ValueError as e:
        sys.exit(f"error: {e}")
    town = build_town(cfg.world.town_seed)
    keys = jax.random.split(jax.random.PRNGKey(FLAGS.seed), FLAGS.num_worlds)
    state = jax.vmap(lambda k: world.reset(k, town, cfg.world))(keys)
    advance = jax.jit(jax.vmap(lambda s, tw: rollout.advance(s, tw, FLAGS.every), in_axes=(0, None)))
    print("| world steps | NPC mean speed (m/s) | NPCs stopped | ego mean speed (m/s) | egos stopped |")
    print("|---|---|---|---|---|")
    for step in range(0, FLAGS.max_steps + 1, FLAGS.every):
        speed_mps = np.asarray(state.veh_speed_mps)  # [worlds, N + 1], the ego is row world.EGO
        npc, ego = np.delete(speed_mps, world.EGO, axis=1), speed_mps[:, world.EGO]
        print(
            f"| {step} | {npc.mean():.2f} | {(npc < STOPPED_MPS).mean():.3f} | {ego.mean():.2f} "
            f"| {(ego < STOPPED_MPS).mean():.3f} |",
            flush=True,
        )
        if step < FLAGS.max_steps:
            state = advance(state, town)


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
