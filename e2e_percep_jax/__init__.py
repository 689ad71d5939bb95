"""End-to-end driving perception by sequential latent representation learning, in JAX.

For other JAX code: ``perceiver, params = e2e_percep_jax.load(workdir)``, then the pure
``perceiver.init`` / ``perceiver.step`` / ``perceiver.boxes`` (see :mod:`e2e_percep_jax.api`), whose outputs
are a ``PerceiverOutputs``.
"""

__all__ = ["Perceiver", "PerceiverOutputs", "load"]


def __getattr__(name):
    # Lazy, so that importing one submodule (e.g. geometry) does not pull in the whole stack.
    if name in __all__:
        from e2e_percep_jax import api

        return getattr(api, name)
    raise AttributeError(f"module 'e2e_percep_jax' has no attribute {name!r}")
