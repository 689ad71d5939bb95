"""What the launchers in ``experiments/`` share: the first call of one that runs the model, and the time
left that their progress lines print.

:func:`prepare` makes the process-wide settings, then the first checks of the launcher's flags. The settings
must come before JAX's backend starts (XLA reads ``XLA_FLAGS`` once, then), and they change the whole
process, so launchers make them and the library never does on import. Launchers that run no model
(``calibrate``, ``odometry_paths``, ``sweep``, ``traffic_soak``, ``warmup_stats``) make the checks alone
(:func:`e2e_percep_jax.config.check_launch`, or :func:`run_config` for one that reads a run).
"""

import sys

from e2e_percep_jax import allocator, xla_cpu
from e2e_percep_jax import config as config_lib


def process_settings(keep_freed_buffers: bool = True, eigen_convolutions: bool = True) -> None:
    """Reuse freed buffers (:mod:`e2e_percep_jax.allocator`), then run convolutions on XLA:CPU's Eigen path
    (:mod:`e2e_percep_jax.xla_cpu`). The benchmark turns either off to measure the default."""
    if keep_freed_buffers:
        allocator.keep_freed_buffers()
    if eigen_convolutions:
        xla_cpu.prefer_eigen_convolutions()


def prepare(argv) -> None:
    """The process-wide settings, then :func:`e2e_percep_jax.config.check_launch` with ``--workdir``
    required: a launcher's first call, inside the ``try`` that turns the ValueError naming a flag into
    its one-line error exit."""
    process_settings()
    config_lib.check_launch(argv)


def run_config(argv, workdir: str) -> config_lib.Config:
    """:func:`e2e_percep_jax.config.check_launch`, then the config of the run in ``workdir``; a bad flag or run
    ends the launcher with one line naming it (status 1)."""
    try:
        config_lib.check_launch(argv)
        return config_lib.run_config(workdir)
    except ValueError as e:
        sys.exit(f"error: {e}")


def eta(seconds: float) -> str:
    """Time left, as a progress line prints it: ``1h05m``, or ``4m09s`` under an hour."""
    m, s = divmod(int(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h}h{m:02d}m" if h else f"{m}m{s:02d}s"
