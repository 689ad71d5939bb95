"""What several families of benchmarks share: the timing rule, the configs measured, a compiled training
step."""

import itertools
import os
import statistics
import time

import jax
from absl import flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import train as train_lib

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
FLAGS = flags.FLAGS


def median_s(fn, repeats, min_total_s=1.0):
    """Median wall time (s) of ``fn()`` after one untimed warm-up run, over ``repeats`` runs or as many
    more as fill ``min_total_s``: a figure of a few ms then gets dozens of runs, so a burst from a
    neighbour on this shared VM moves its median less."""
    jax.block_until_ready(fn())
    times = []
    while len(times) < repeats or sum(times) < min_total_s:
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def train_size(spec: str) -> tuple:
    """(B, T, R) of a ``--train_sizes`` entry ``BxTxR``."""
    try:
        b, t, r = (int(v) for v in spec.split("x"))
    except ValueError:
        raise ValueError(f"--train_sizes: {spec!r} is not BxTxR (three integers)") from None
    return b, t, r


def paper_config(batch_size, seq_len, image_size):
    """The paper's network (default widths, the vector latent) at the given (B, T, R), without the place
    stream: the peer's model and batch (``--what=place`` adds the stream)."""
    return config_lib.validate(
        config_lib.replace(
            config_lib.get_config("paper"),
            data=dict(batch_size=batch_size, seq_len=seq_len, image_size=image_size, place_frames=0),
            model=dict(latent="vector"),
        )
    )


def latent_models(base: config_lib.Config) -> dict:
    """``base`` with each latent (``config.LATENTS``), the bird-eye grid at each ``--grid_cells``,
    ``--grid_warps``, ``--grid_motions`` and ``--grid_memory_channels``: {the figure's name ("vector", "bev,
    16 cells", "bev, 16 cells, lattice", "bev, 16 cells, lattice, flow", "bev, 16 cells, memory 16", ...):
    config}. A taught or carried flow trains with its term (``--train.flow_weight=1``)."""
    models = {"vector": config_lib.replace(base, model=dict(latent="vector"))}
    for cells, warp, motion, memory in itertools.product(
        FLAGS.grid_cells, FLAGS.grid_warps, FLAGS.grid_motions, FLAGS.grid_memory_channels
    ):
        name = f"bev, {cells} cells" + ("" if warp == "bilinear" else f", {warp}")
        name += "" if motion == "ego" else ", " + motion.removeprefix("ego_and_").replace("_", " ")
        name += f", memory {memory}" if int(memory) else ""
        grid = dict(
            latent="bev", grid_cells=int(cells), grid_warp=warp, grid_motion=motion, grid_memory_channels=int(memory)
        )
        taught = dict(train=dict(flow_weight=1.0)) if motion in config_lib.TAUGHT_FLOW_MOTIONS else {}
        models[name] = config_lib.replace(base, model=grid, **taught)
    return models


def cpu_stream_config():
    """The ``cpu`` preset, its stream's K replaced by ``--batches_per_drive`` if given."""
    cfg = config_lib.get_config("cpu")
    return config_lib.replace(cfg, data=dict(batches_per_drive=FLAGS.batches_per_drive or cfg.data.batches_per_drive))


def train_step_runner(cfg, batch):
    """(compile seconds, a function running one compiled training step, on ``batch`` unless given another,
    the compiled program)."""
    mesh = train_lib.make_mesh()
    step_fn = train_lib.make_train_step(cfg, mesh)
    holder = {"state": train_lib.init_state(cfg)}
    batch = train_lib.shard_batch(batch, mesh, cfg)
    key = jax.random.PRNGKey(0)
    start = time.perf_counter()
    compiled = step_fn.lower(holder["state"], batch, key).compile()
    compile_s = time.perf_counter() - start

    def run(step_batch=batch):
        holder["state"], metrics = compiled(holder["state"], step_batch, key)  # the state is donated
        return metrics["total"]

    return compile_s, run, compiled
