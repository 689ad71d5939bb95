"""Run XLA:CPU's single convolutions on its Eigen path instead of its YNN fusion: faster for this model.

XLA:CPU (jaxlib 0.10 and 0.12) hands convolutions of 16 or more channels (above a small size) to its
YNN library by default. For this model's convolutions (3 x 3 and 5 x 5, 32-256 channels, stride 2)
Eigen's path is faster, forward and backward: the measurements are in ``experiments/bench.py``
(``--what=train`` with and without ``--eigen_convolutions``). Only float rounding changes (relative
~1e-6).

XLA reads ``XLA_FLAGS`` once, when its backend starts (the first computation), so
:func:`prefer_eigen_convolutions` must run before that: the launchers in ``experiments/`` and
``e2e.load`` call it first. It edits XLA's default instead of replacing it (the leading ``-``), and it
never overrides a choice already made: if ``XLA_FLAGS`` names the flag, it is left as it is, so
``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=+individual_convolution`` keeps XLA's own default.
An XLA that does not know the flag aborts at start-up, so it is set only for the jaxlib versions where
it was measured (:data:`MEASURED_JAXLIB`).
"""

import os

FLAG = "--xla_cpu_experimental_ynn_fusion_type"
VALUE = "-individual_convolution"  # remove single convolutions from the YNN fusion types
# [first, past-last) jaxlib (major, minor) where the flag and its value were measured; the flag is absent
# before 0.9. A newer jaxlib keeps XLA's default until it is measured and this bound raised.
MEASURED_JAXLIB = ((0, 10), (0, 13))


def jaxlib_measured() -> bool:
    """Whether the installed jaxlib is in :data:`MEASURED_JAXLIB` (reads a version string only:
    importing ``jaxlib.version`` starts no backend)."""
    from jaxlib import version

    first, past_last = MEASURED_JAXLIB
    return first <= tuple(version.__version_info__[:2]) < past_last


def prefer_eigen_convolutions() -> bool:
    """Adds ``FLAG=VALUE`` to ``XLA_FLAGS`` for this process and its children. Returns whether it did:
    False where ``XLA_FLAGS`` already names the flag, where ``JAX_PLATFORMS`` names no CPU, or where
    jaxlib is outside :data:`MEASURED_JAXLIB`. Without effect once a computation has run
    (:func:`convolution_path` tells which path is in use)."""
    flags = os.environ.get("XLA_FLAGS", "")
    platforms = os.environ.get("JAX_PLATFORMS", "")
    if FLAG in flags or (platforms and "cpu" not in platforms.lower().split(",")) or not jaxlib_measured():
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}={VALUE}".strip()
    return True


def convolution_path() -> str:
    """Which path this process's convolutions take: "ynn" or "eigen" on the CPU, read from the compiled
    program of one convolution of the size YNN takes by default (compiling it takes ~0.3 s and starts
    the backend), else the backend's name."""
    import jax
    import jax.numpy as jnp

    if jax.default_backend() != "cpu":
        return jax.default_backend()
    x = jax.ShapeDtypeStruct((8, 32, 32, 32), jnp.float32)
    w = jax.ShapeDtypeStruct((3, 3, 32, 64), jnp.float32)
    conv = lambda x, w: jax.lax.conv_general_dilated(x, w, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return "ynn" if "ynn_fusion" in jax.jit(conv).lower(x, w).compile().as_text() else "eigen"
