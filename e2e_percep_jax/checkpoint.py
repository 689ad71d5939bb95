"""Restoring a training run's parameters from its orbax checkpoints (no evaluation code, no cv2)."""
import os

import jax
import orbax.checkpoint as ocp

from e2e_percep_jax import train as train_lib
from e2e_percep_jax.config import Config, run_config


def restore_params(workdir: str, cfg: Config | None = None, step: int | None = None, objective=None):
    """(cfg, params, step) of the run in ``workdir``: its config.json (unless ``cfg`` is given) and the
    params of checkpoint ``step`` (default: the latest), restored with the same abstract train state
    that ``train.train`` saves for ``objective`` (a ``train.Objective``; default: the perception
    model). Raises FileNotFoundError if there is no checkpoint."""
    workdir = os.path.abspath(workdir)
    cfg = run_config(workdir) if cfg is None else cfg
    options = ocp.CheckpointManagerOptions(read_only=True, create=False)
    with ocp.CheckpointManager(os.path.join(workdir, "checkpoints"), options=options) as manager:
        saved = manager.all_steps()
        if not saved:
            raise FileNotFoundError(f"no checkpoint in {workdir}/checkpoints")
        if step is not None and step not in saved:
            raise ValueError(f"--step={step}: {workdir} has checkpoints at steps {sorted(saved)}")
        step = max(saved) if step is None else step
        sharding = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding),
                                jax.eval_shape(lambda: train_lib.init_state(cfg, objective or train_lib.PERCEPTION)))
        try:
            state = manager.restore(step, args=ocp.args.StandardRestore(abstract))
        except Exception as e:  # orbax raises many types (decode, data loss, tree or shape mismatch): one line
            raise ValueError(f"{workdir}/checkpoints/{step}: cannot be restored for its config.json (damaged, or "
                             f"written by another config): {train_lib.restore_failure(e)}") from None
    return cfg, state.params, step
