"""e2e_percep_jax: end-to-end driving perception by sequential latent representation learning.

Layout follows the data: town/world (traffic) -> sensors -> batch -> model -> loss -> train -> evaluate.
"""
