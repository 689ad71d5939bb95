"""The driving world: everything that simulates and observes, in pure JAX, and nothing of the model.

In the order the data flows: ``geometry`` (frames, boxes, the bird-eye grid), ``town`` (the static town,
NumPy, built once per seed), ``world`` (traffic and the ego plant: ``reset``, ``step``), ``motion`` (the
ego's motion as an estimator models it), ``odometry`` (the ego pose integrated from measured speed and yaw
rate through motion's step), ``sensors`` (camera, lidar, roadmap: ``observe``), ``pixor``
(detection targets), ``rollout`` (the loop that drives a world and observes it) and ``batch`` (training
batches, made on the fly). Used on its own, as a simulator::

    import jax
    from e2e_percep_jax.config import WorldConfig
    from e2e_percep_jax.sim import rollout, town, world

    t = town.build_town(0)
    state = world.reset(jax.random.PRNGKey(0), t, WorldConfig())
    state, frames = rollout.drive(state, t, num_frames=100, image_size=64)  # jit and vmap it as you like

Importing this package imports none of its modules, so ``e2e_percep_jax.sim.motion`` stays light.
"""
