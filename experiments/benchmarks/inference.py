"""The perceiver's benchmarks: one filtering step with every decoder, and the whole online evaluation."""

import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import evaluate as evaluate_lib
from e2e_percep_jax import model as model_lib

from .common import latent_models, median_s, paper_config

FLAGS = flags.FLAGS


def bench_infer(town, repeats):
    """One filtering step plus every decoder, paper config at R = 128, with each latent
    (``common.latent_models``): latency at batch 1, throughput at ``--infer_batch``."""
    figures = []
    for latent, cfg in latent_models(paper_config(1, 10, 128)).items():
        params = model_lib.init_params(jax.random.PRNGKey(0), cfg)

        @jax.jit
        def infer(params, state, camera, lidar, prev_action, cfg=cfg):
            state, out = model_lib.filter_step(params, state, camera, lidar, prev_action, None, cfg)
            return state, model_lib.decode(params, out, cfg)

        figure = {"image_size": 128, "network": latent}
        for n in (1, FLAGS.infer_batch):
            image = jnp.asarray(np.random.default_rng(0).integers(0, 256, (n, 128, 128, 3), np.uint8))
            state = model_lib.init_filter_state(n, cfg)
            step_s = median_s(lambda: infer(params, state, image, image, jnp.zeros((n, 2))), repeats)
            if n == 1:
                figure["latency_ms_batch1"] = 1e3 * step_s
            else:
                figure.update(batch=n, frames_per_s=n / step_s)
        figures.append(figure)
    return {"sizes": figures}


def bench_eval(town, repeats):
    """Wall time of the whole online evaluation at the ``cpu`` config (15,000 frames; compile included,
    no video), untrained parameters: the cost does not depend on their values."""
    del town, repeats  # one run: it is minutes long, and it builds its own towns
    cfg = config_lib.get_config("cpu")
    params = model_lib.init_params(jax.random.PRNGKey(0), cfg)
    with tempfile.TemporaryDirectory() as out_dir:
        start = time.perf_counter()
        evaluate_lib.evaluate(cfg, params, out_dir, video_frames=0, log=lambda _: None)
        return {"config": "cpu", "eval_frames": cfg.eval.num_frames, "wall_s": time.perf_counter() - start}
