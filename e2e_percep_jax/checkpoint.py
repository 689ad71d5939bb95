"""Restoring a training run's parameters from its orbax checkpoints (no evaluation code, no cv2)."""
import os

import jax

from e2e_percep_jax import train as train_lib
from e2e_percep_jax.config import Config, MissingRunFileError, run_config


def restore_params(workdir: str, cfg: Config | None = None, step: int | None = None, objective=None):
    """(cfg, params, step) of the run in ``workdir``: its config.json (unless ``cfg`` is given) and the
    params of checkpoint ``step`` (default: the latest), restored with the same abstract train state
    that ``train.train`` saves for ``objective`` (a ``train.Objective``; default: the perception
    model). Raises MissingRunFileError (a ValueError) if there is no checkpoint, ValueError (one line,
    naming the checkpoint) if ``step`` is not saved or cannot be restored; writes nothing."""
    workdir = os.path.abspath(workdir)
    cfg = run_config(workdir) if cfg is None else cfg
    saved = train_lib.saved_steps(workdir)
    if not saved:
        raise MissingRunFileError(f"no checkpoint in {workdir}/checkpoints")
    if step is not None and step not in saved:
        raise ValueError(f"--step={step}: {workdir} has checkpoints at steps {saved}")
    step = saved[-1] if step is None else step
    sharding = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding),
                            jax.eval_shape(lambda: train_lib.init_state(cfg, objective or train_lib.PERCEPTION)))
    state = train_lib.read_checkpoint(workdir, step, abstract)
    return cfg, state.params, step
