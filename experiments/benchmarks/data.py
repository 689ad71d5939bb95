"""The data's benchmarks: world steps, sensor frames (whole and by sensor), and training batches against
the training step they feed."""

import itertools
import os
import statistics
import time

import jax
import jax.numpy as jnp
from absl import flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import train as train_lib
from e2e_percep_jax.sim import batch as batch_lib
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import pixor, rollout, sensors, world

from .common import cpu_stream_config, median_s, train_step_runner

FLAGS = flags.FLAGS
FRAMES_SECONDS = 6  # the frames figure's one-second blocks


def _warm_worlds(town, num_worlds, cfg):
    """``num_worlds`` worlds with steady traffic, as a batch's warm-up leaves them."""
    cfg = config_lib.replace(cfg, data=dict(batch_size=num_worlds))
    return jax.jit(batch_lib.warm_up, static_argnames="cfg")(jax.random.PRNGKey(0), town, cfg)


def bench_world(town, repeats):
    """World-steps/s: W worlds of 100 vehicles advanced by dt, 100 steps per timed run."""
    cfg, steps = config_lib.get_config("paper"), 100
    states = _warm_worlds(town, FLAGS.num_worlds, cfg)
    run = jax.jit(jax.vmap(lambda s: rollout.advance(s, town, steps)))
    median = median_s(lambda: run(states), repeats)
    return {
        "num_worlds": FLAGS.num_worlds,
        "num_vehicles": cfg.world.num_vehicles,
        "steps_per_run": steps,
        "world_steps_per_s": FLAGS.num_worlds * steps / median,
    }


def bench_frames(town, repeats):
    """Full frames/s: ``sensors.observe`` (every contract key but the lidar scan, which training batches
    skip: its cost is :func:`bench_frames_parts`' ``lidar_scan``) on W world states at once.

    This VM's speed swings by up to 2x from one second to the next, so
    the figure is the median over FRAMES_SECONDS one-second blocks, and the slowest and fastest block's
    medians show the spread."""
    cfg, r = config_lib.get_config("paper"), FLAGS.frames_image_size
    states = _warm_worlds(town, FLAGS.num_worlds, cfg)
    observe = jax.jit(jax.vmap(lambda s: sensors.observe(s, town, r, scan=False)))
    blocks_s = [median_s(lambda: observe(states), repeats) for _ in range(FRAMES_SECONDS)]
    per_s = lambda seconds: FLAGS.num_worlds / seconds
    return {
        "image_size": r,
        "frames_at_once": FLAGS.num_worlds,
        "frames_per_s": per_s(statistics.median(blocks_s)),
        "slowest_second_frames_per_s": per_s(max(blocks_s)),
        "fastest_second_frames_per_s": per_s(min(blocks_s)),
    }


def bench_frames_parts(town, repeats):
    """Where a frame's time goes: each sensor of ``sensors.observe`` alone, vmapped over W states, as
    core-microseconds per frame (wall time x cores / frames), so the parts but ``lidar_scan`` add up to
    ``frames``."""
    cfg, r = config_lib.get_config("paper"), FLAGS.frames_image_size
    states = _warm_worlds(town, FLAGS.num_worlds, cfg)
    town_j = jax.tree.map(jnp.asarray, town)

    def in_ego_frame(state):
        ego = state.veh_box[world.EGO]
        return (
            ego,
            geo.box_to_ego(state.veh_box[1:], ego[:2], ego[2]),
            geo.box_to_ego(town_j.building_box, ego[:2], ego[2]),
        )

    def lidar(state):
        _, boxes, buildings = in_ego_frame(state)
        return sensors.render_lidar(sensors.lidar_obstacles(state, town_j, buildings, boxes), r)

    def lidar_scan(state):
        _, boxes, buildings = in_ego_frame(state)
        return sensors.render_scan(sensors.scan_obstacles(state, town_j, buildings, boxes))

    def camera(state):
        ego, boxes, buildings = in_ego_frame(state)
        return sensors.render_camera(
            sensors.camera_obstacles(state, town_j, buildings, boxes), town_j, ego[:2], ego[2], r
        )

    def roadmap(state):
        ego = state.veh_box[world.EGO]
        return sensors.render_roadmap(town_j, ego[:2], ego[2], ego[3], ego[4], r)

    parts = {
        "lidar": lidar,
        "lidar_scan": lidar_scan,
        "camera": camera,
        "roadmap": roadmap,
        "pixor_targets": lambda state: pixor.targets(in_ego_frame(state)[1], r),
    }
    figure = {"image_size": r, "frames_at_once": FLAGS.num_worlds}
    for name, fn in parts.items():
        run = jax.jit(jax.vmap(fn))
        figure[f"{name}_core_us_per_frame"] = (
            1e6 * os.cpu_count() * median_s(lambda: run(states), repeats) / FLAGS.num_worlds
        )
    return figure


def bench_batch(town, repeats):
    """Making one training batch vs one training step, at the ``cpu`` config (target: < 10 %): the preset's
    stream (``batches_per_drive`` K) and fresh worlds for every batch (K = 1)."""
    cfg = cpu_stream_config()
    per_drive = cfg.data.batches_per_drive
    key = jax.random.PRNGKey(0)
    fresh_batch_s = median_s(lambda: batch_lib.make_batch(key, town, cfg), repeats)
    _, run, _ = train_step_runner(cfg, batch_lib.make_batch(key, town, cfg))
    step_s = median_s(run, repeats)

    # The stream's first K batches are K warm-ups: time a whole cycle (K^2 batches: K drives, each its
    # warm-up and K segments, served in turn).
    def cycle():
        stream = batch_lib.batch_stream(town, cfg, seed=0)
        return [b["camera"] for _, b in itertools.islice(stream, per_drive**2)]

    stream_batch_s = median_s(cycle, repeats) / per_drive**2
    return {
        "config": "cpu",
        "train_step_s": step_s,
        "batches_per_drive": per_drive,
        "stream_batch_s": stream_batch_s,
        "stream_batch_over_step": stream_batch_s / step_s,
        "fresh_batch_s": fresh_batch_s,
        "fresh_batch_over_step": fresh_batch_s / step_s,
    }


def bench_loop(town, repeats):
    """The batch's share as training meets it: seconds per step of a loop that dispatches like
    ``train.train`` (a batch, its sharding, then a step, no wait in between), fed by the ``cpu`` preset's
    stream against one fixed batch, each over a whole cycle of K^2 steps; pairs alternate, medians over
    ``repeats`` // 2 pairs (at least 2)."""
    cfg = cpu_stream_config()
    per_drive = cfg.data.batches_per_drive
    fixed = batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg)
    _, train_step, _ = train_step_runner(cfg, fixed)
    steps, mesh = per_drive**2, train_lib.make_mesh()

    def run(batches):
        start = time.perf_counter()
        jax.block_until_ready(
            [train_step(train_lib.shard_batch(batch, mesh, cfg)) for _, batch in itertools.islice(batches, steps)]
        )
        return (time.perf_counter() - start) / steps

    run(batch_lib.batch_stream(town, cfg, seed=0))  # compiles the stream's functions
    fixed_s, stream_s = [], []
    for pair in range(max(2, repeats // 2)):
        fixed_s.append(run(itertools.repeat((None, fixed))))
        stream_s.append(run(batch_lib.batch_stream(town, cfg, seed=0, start_step=(pair + 1) * steps)))
    fixed_s, stream_s = statistics.median(fixed_s), statistics.median(stream_s)
    return {
        "config": "cpu",
        "batches_per_drive": per_drive,
        "steps_per_run": steps,
        "fixed_batch_step_s": fixed_s,
        "stream_step_s": stream_s,
        "stream_overhead": stream_s / fixed_s - 1,
    }
