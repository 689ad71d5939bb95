"""Benchmarks: every performance figure of the lab notebook, measured the same way each time.

    python experiments/bench.py                      # every figure (world ... memory, see BENCHMARKS)
    python experiments/bench.py --what=train --train_sizes=8x10x64 --repeats=7

Each figure is the median of ``--repeats`` timed runs after a warm-up (compilation excluded and
reported separately); ``eval`` and ``memory`` are one run each (minutes long). Each benchmark prints
one JSON line and writes it to ``--out_dir/<name>.json``; a table of all of them closes the run.
``train`` also runs the eager PyTorch peer (``../shared/peer/torch_peer_bench.py``, with
``--peer_python``) at the same (B, T, R) right after ours and reports ``ratio_vs_peer`` = our
frames/s over the peer's. ``frames_parts`` and ``train_parts`` are the profiles behind ``frames`` and
``train``: the same work split into its parts; ``train_profile`` is the step's per-op profile beside the
peer's. ``--noeigen_convolutions`` measures XLA's default convolution path instead of the launchers'.
"""

import bisect
import collections
import glob
import itertools
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from flax import linen as nn

from e2e_percep_jax import allocator, xla_cpu
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import evaluate as evaluate_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax import train as train_lib
from e2e_percep_jax.sim import batch as batch_lib
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import pixor, rollout, sensors, world
from e2e_percep_jax.sim.town import build_town

BENCHMARKS = (
    "world",
    "frames",
    "frames_parts",
    "batch",
    "loop",
    "train",
    "place",
    "train_parts",
    "train_profile",
    "deconv",
    "infer",
    "compile",
    "eval",
    "memory",
)
_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PEER_SCRIPT = os.path.join(_REPO, "..", "shared", "peer", "torch_peer_bench.py")

flags.DEFINE_list("what", list(BENCHMARKS), f"benchmarks to run, any of {BENCHMARKS}")
flags.DEFINE_string("out_dir", "runs/bench", "one <benchmark>.json per figure goes here")
flags.DEFINE_integer(
    "repeats", 5, "timed runs per figure, at least (short figures get more, to fill 1 s); the median is reported"
)
flags.DEFINE_list("train_sizes", ["8x10x64", "4x10x128"], "BxTxR of the training-step figures")
flags.DEFINE_integer("peer_rounds", 3, "train: rounds of (ours, the peer) alternated, each of --repeats steps")
flags.DEFINE_string(
    "peer_python",
    os.path.join(_REPO, ".venv-peer", "bin", "python"),
    "python with torch for the peer benchmark; empty: skip the peer",
)
flags.DEFINE_integer("num_worlds", 32, "worlds stepped in parallel (world) / frames observed at once (frames)")
flags.DEFINE_integer("frames_image_size", 128, "R of the frames benchmark")
flags.DEFINE_list("compile_seq_lens", ["10", "50"], "T values of the paper-config compile-time figure")
flags.DEFINE_integer("infer_batch", 64, "batch of the inference throughput figure (latency is at batch 1)")
flags.DEFINE_integer(
    "batches_per_drive", None, "K of the batch figure's stream (drives feed K batches each); default: the cpu preset's"
)
flags.DEFINE_list("place_frames", ["32"], "place: P of the place stream's figures, beside P = 0")
flags.DEFINE_integer("memory_steps", 300, "training steps of the cpu-config run whose resident memory is sampled")
flags.DEFINE_boolean(
    "keep_freed_buffers",
    True,
    "reuse freed buffers as the launchers do (allocator.py), "
    "here and in the peer; --nokeep_freed_buffers measures glibc's default",
)
flags.DEFINE_boolean(
    "eigen_convolutions",
    True,
    "run convolutions on XLA:CPU's Eigen path as the launchers do "
    "(xla_cpu.py); --noeigen_convolutions measures XLA's default",
)
FLAGS = flags.FLAGS


def _median_s(fn, repeats, min_total_s=1.0):
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


def _size(spec: str) -> tuple:
    """(B, T, R) of a ``--train_sizes`` entry ``BxTxR``."""
    try:
        b, t, r = (int(v) for v in spec.split("x"))
    except ValueError:
        raise ValueError(f"--train_sizes: {spec!r} is not BxTxR (three integers)") from None
    return b, t, r


def _paper_config(batch_size, seq_len, image_size):
    """The paper's network (default widths) at the given (B, T, R), without the place stream: the peer's
    model and batch (``--what=place`` adds the stream)."""
    return config_lib.validate(
        config_lib.replace(
            config_lib.get_config("paper"),
            data=dict(batch_size=batch_size, seq_len=seq_len, image_size=image_size, place_frames=0),
        )
    )


def _warm_worlds(town, num_worlds, cfg):
    """``num_worlds`` worlds with steady traffic, as a batch's warm-up leaves them."""
    cfg = config_lib.replace(cfg, data=dict(batch_size=num_worlds))
    return jax.jit(batch_lib.warm_up, static_argnames="cfg")(jax.random.PRNGKey(0), town, cfg)


def bench_world(town, repeats):
    """World-steps/s: W worlds of 100 vehicles advanced by dt, 100 steps per timed run."""
    cfg, steps = config_lib.get_config("paper"), 100
    states = _warm_worlds(town, FLAGS.num_worlds, cfg)
    run = jax.jit(jax.vmap(lambda s: rollout.advance(s, town, steps)))
    median = _median_s(lambda: run(states), repeats)
    return {
        "num_worlds": FLAGS.num_worlds,
        "num_vehicles": cfg.world.num_vehicles,
        "steps_per_run": steps,
        "world_steps_per_s": FLAGS.num_worlds * steps / median,
    }


FRAMES_SECONDS = 6  # the frames figure's one-second blocks


def bench_frames(town, repeats):
    """Full frames/s: ``sensors.observe`` (every contract key) on W world states at once.

    This VM's speed swings by up to 2x from one second to the next, so
    the figure is the median over FRAMES_SECONDS one-second blocks, and the slowest and fastest block's
    medians show the spread."""
    cfg, r = config_lib.get_config("paper"), FLAGS.frames_image_size
    states = _warm_worlds(town, FLAGS.num_worlds, cfg)
    observe = jax.jit(jax.vmap(lambda s: sensors.observe(s, town, r)))
    blocks_s = [_median_s(lambda: observe(states), repeats) for _ in range(FRAMES_SECONDS)]
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
    core-microseconds per frame (wall time x cores / frames), so the parts add up to ``frames``."""
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
        "camera": camera,
        "roadmap": roadmap,
        "pixor_targets": lambda state: pixor.targets(in_ego_frame(state)[1], r),
    }
    figure = {"image_size": r, "frames_at_once": FLAGS.num_worlds}
    for name, fn in parts.items():
        run = jax.jit(jax.vmap(fn))
        figure[f"{name}_core_us_per_frame"] = (
            1e6 * os.cpu_count() * _median_s(lambda: run(states), repeats) / FLAGS.num_worlds
        )
    return figure


def _train_step_runner(cfg, batch):
    """(compile seconds, a function running one compiled training step, on ``batch`` unless given another,
    the compiled program)."""
    mesh = train_lib.make_mesh()
    step_fn = train_lib.make_train_step(cfg, mesh)
    holder = {"state": train_lib.init_state(cfg)}
    batch = train_lib.shard_batch(batch, mesh)
    key = jax.random.PRNGKey(0)
    start = time.perf_counter()
    compiled = step_fn.lower(holder["state"], batch, key).compile()
    compile_s = time.perf_counter() - start

    def run(step_batch=batch):
        holder["state"], metrics = compiled(holder["state"], step_batch, key)  # the state is donated
        return metrics["total"]

    return compile_s, run, compiled


def _cpu_stream_config():
    """The ``cpu`` preset, its stream's K replaced by ``--batches_per_drive`` if given."""
    cfg = config_lib.get_config("cpu")
    return config_lib.replace(cfg, data=dict(batches_per_drive=FLAGS.batches_per_drive or cfg.data.batches_per_drive))


def bench_batch(town, repeats):
    """Making one training batch vs one training step, at the ``cpu`` config (target: < 10 %): the preset's
    stream (``batches_per_drive`` K) and fresh worlds for every batch (K = 1)."""
    cfg = _cpu_stream_config()
    per_drive = cfg.data.batches_per_drive
    key = jax.random.PRNGKey(0)
    fresh_batch_s = _median_s(lambda: batch_lib.make_batch(key, town, cfg), repeats)
    _, run, _ = _train_step_runner(cfg, batch_lib.make_batch(key, town, cfg))
    step_s = _median_s(run, repeats)

    # The stream's first K batches are K warm-ups: time a whole cycle (K^2 batches: K drives, each its
    # warm-up and K segments, served in turn).
    def cycle():
        stream = batch_lib.batch_stream(town, cfg, seed=0)
        return [b["camera"] for _, b in itertools.islice(stream, per_drive**2)]

    stream_batch_s = _median_s(cycle, repeats) / per_drive**2
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
    cfg = _cpu_stream_config()
    per_drive = cfg.data.batches_per_drive
    fixed = batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg)
    _, train_step, _ = _train_step_runner(cfg, fixed)
    steps, mesh = per_drive**2, train_lib.make_mesh()

    def run(batches):
        start = time.perf_counter()
        jax.block_until_ready(
            [train_step(train_lib.shard_batch(batch, mesh)) for _, batch in itertools.islice(batches, steps)]
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


def _run_peer(script, *args):
    """The last stdout line of ``script`` run by ``--peer_python``, as JSON; None without a peer python."""
    if not FLAGS.peer_python or not os.path.exists(FLAGS.peer_python):
        return None
    # The peer's allocator keeps freed buffers as ours does (allocator.py), so neither pays page faults the other does not.
    out = subprocess.run(
        [FLAGS.peer_python, script, *map(str, args)],
        check=True,
        capture_output=True,
        text=True,
        env={**os.environ, "GLIBC_TUNABLES": allocator.GLIBC_TUNABLES if FLAGS.keep_freed_buffers else ""},
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def _peer(batch_size, seq_len, image_size, repeats):
    return _run_peer(
        PEER_SCRIPT, "--batch", batch_size, "--seq-len", seq_len, "--image-size", image_size, "--steps", repeats
    )


def bench_train(town, repeats):
    """Training-step frames/s (B·(T+1) per step) at the paper's widths, beside the eager PyTorch peer:
    ``--peer_rounds`` rounds of ours then the peer's, ``repeats`` steps each, so that a slow spell of this
    shared VM falls on both; each side's figure is the median of its rounds' medians."""
    figures = []
    for size in FLAGS.train_sizes:
        b, t, r = _size(size)
        cfg = _paper_config(b, t, r)
        compile_s, run, _ = _train_step_runner(cfg, batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg))
        ours_s, peers = [], []
        for _ in range(FLAGS.peer_rounds):
            ours_s.append(_median_s(run, repeats))
            peers.append(_peer(b, t, r, repeats))
        step_s = statistics.median(ours_s)
        params = sum(x.size for x in jax.tree.leaves(jax.eval_shape(model_lib.init_params, jax.random.PRNGKey(0), cfg)))
        figure = {
            "batch": b,
            "seq_len": t,
            "image_size": r,
            "params": params,
            "compile_s": compile_s,
            "step_s_median": step_s,
            "step_s_rounds": ours_s,
            "frames_per_s": b * (t + 1) / step_s,
        }
        if peers[0] is not None:
            peer_s = [peer["step_s_median"] for peer in peers]
            figure.update(
                peer_step_s_median=statistics.median(peer_s),
                peer_step_s_rounds=peer_s,
                peer_frames_per_s=b * (t + 1) / statistics.median(peer_s),
                peer_params=peers[0]["params"],
                peer_threads=peers[0]["threads"],
                ratio_vs_peer=statistics.median(peer_s) / step_s,
                ratio_vs_peer_rounds=[p / o for p, o in zip(peer_s, ours_s)],
            )
        figures.append(figure)
    return {"sizes": figures}


def bench_place(town, repeats):
    """The place stream's cost: seconds per training step (batch, sharding and step, dispatched as
    ``train.train`` does, over the preset's stream) without it and with each ``--place_frames`` P, for the
    ``cpu`` preset's network and for the paper's widths at the ``cpu`` preset's (B, T, R), the latter
    alternated with the eager PyTorch peer (the same network, no place stream) for ``--peer_rounds``
    rounds, so that each ratio is taken in one window of this shared VM."""
    cpu = _cpu_stream_config()
    b, t, r = cpu.data.batch_size, cpu.data.seq_len, cpu.data.image_size
    paper = config_lib.replace(_paper_config(b, t, r), data=dict(batches_per_drive=cpu.data.batches_per_drive))
    mesh, sizes = train_lib.make_mesh(), [0, *map(int, FLAGS.place_frames)]
    figures = []
    for name, base in (("cpu", cpu), ("paper widths", paper)):
        runners = {}
        for p in sizes:
            cfg = config_lib.replace(base, data=dict(place_frames=p))
            stream = batch_lib.batch_stream(town, cfg, seed=0)
            runners[p] = (_train_step_runner(cfg, next(stream)[1])[1], stream)

        def run(p):
            step, stream = runners[p]
            return _median_s(lambda: step(train_lib.shard_batch(next(stream)[1], mesh)), repeats)

        rounds, peers = {p: [] for p in sizes}, []
        for _ in range(FLAGS.peer_rounds):
            for p in sizes:
                rounds[p].append(run(p))
            if base is paper:
                peers.append(_peer(b, t, r, repeats))
        figure = {"network": name, "batch": b, "seq_len": t, "image_size": r}
        for p, times in rounds.items():
            figure[f"step_s_place{p}"] = statistics.median(times)
            figure[f"step_s_place{p}_rounds"] = times
            if p:
                figure[f"place{p}_over_no_place"] = statistics.median([x / x0 for x, x0 in zip(times, rounds[0])])
        if peers and peers[0] is not None:
            figure["peer_step_s_median"] = statistics.median(peer["step_s_median"] for peer in peers)
            for p, times in rounds.items():
                figure[f"ratio_vs_peer_place{p}"] = statistics.median(
                    [peer["step_s_median"] / x for peer, x in zip(peers, times)]
                )
        figures.append(figure)
    return {"sizes": figures}


def bench_train_parts(town, repeats):
    """Where a training step's time goes, at the first ``--train_sizes`` entry: forward + backward of
    (a) the whole loss, (b) the two encoders and the latent scan alone, (c) every decoder alone on fixed
    latents. Each part's gradient is of the sum of its outputs, so it costs what the loss's would."""
    b, t, r = _size(FLAGS.train_sizes[0])
    cfg = _paper_config(b, t, r)
    params = model_lib.init_params(jax.random.PRNGKey(0), cfg)
    batch = batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg)
    key = jax.random.PRNGKey(1)
    total = lambda tree: sum(jnp.sum(x) for x in jax.tree.leaves(tree))
    z = jnp.zeros((b * (t + 1), cfg.model.z1_dim + cfg.model.z2_dim))
    parts = {
        "loss": lambda p: train_lib.loss_lib.loss_fn(p, batch, key, cfg)[0],
        "encoders_and_scan": lambda p: total(
            model_lib.filter_sequence(p, batch["camera"], batch["lidar"], batch["action"], key, cfg)
        ),
        "decoders": lambda p: total(model_lib.decode(p, z, cfg)),
    }
    figure = {"batch": b, "seq_len": t, "image_size": r}
    for name, fn in parts.items():
        grad = jax.jit(jax.grad(fn))
        figure[f"{name}_s"] = _median_s(lambda: grad(params), repeats)
    return figure


# The parts of a training step, each named by what its ops' HLO metadata (op_name: the jit and flax scopes
# they were traced in) contains; the first match wins. An op with op_name but no match is the optimizer's
# (the update after the gradient: Adam, clipping, the finite-step guard); one without op_name was made by
# XLA itself ("made by XLA": layout-changing copies and transposes, convolutions it rewrote).
PROFILE_PARTS = (
    ("encoders", "_encoder/"),
    ("latent scan", "while/body"),
    ("decoders", "PerceptionModel.decode"),
    ("pose belief", "pose_belief"),
    ("losses", "loss_fn"),
)


def _op_parts(hlo_text):
    """{HLO instruction name: part} of a compiled program's text."""
    parts = {}
    for line in hlo_text.splitlines():
        name = re.match(r"\s*(?:ROOT )?%([\w.-]+) = ", line)
        if name:
            op_name = re.search(r'op_name="([^"]*)"', line)
            parts[name.group(1)] = (
                "made by XLA"
                if op_name is None
                else next((part for part, scope in PROFILE_PARTS if scope in op_name.group(1)), "optimizer")
            )
    return parts


def _op_core_ns(profile):
    """{HLO op: core-ns} of an XLA:CPU trace. An op's time is its runtime thunk's (a trace event with an
    ``hlo_op`` stat) plus that of the thread-pool tasks it started (convolutions return before their work
    is done): a task (a StartRegion ... StopRegion span on a pool thread) belongs to the op running where
    its ``Record`` event (same id) was logged, followed up through tasks that started tasks. Task time
    inside an op's own event is not counted twice; task time that leads to no op is returned as None."""
    ops, tasks, records = collections.defaultdict(list), collections.defaultdict(list), {}
    for plane in profile.planes:
        for index, line in enumerate(plane.lines):
            where, opened = (plane.name, index), None
            for event in sorted(line.events, key=lambda e: e.start_ns):
                stats = dict(event.stats)
                if "hlo_op" in stats:
                    ops[where].append((event.start_ns, event.end_ns, stats["hlo_op"]))
                elif event.name == "ThreadpoolListener::Record":
                    records[stats["_p"]] = (where, event.start_ns)
                elif event.name == "ThreadpoolListener::StartRegion":
                    opened = (event.start_ns, stats["_c"])
                elif event.name == "ThreadpoolListener::StopRegion" and opened is not None:
                    tasks[where].append((opened[0], event.start_ns, opened[1]))
                    opened = None

    def span_at(spans, t):
        i = bisect.bisect_right(spans, (t, math.inf)) - 1
        return spans[i] if i >= 0 and spans[i][0] <= t <= spans[i][1] else None

    def owner(task_id, depth=0):
        if task_id not in records or depth > 64:
            return None
        where, t = records[task_id]
        op = span_at(ops.get(where, []), t)
        if op is not None:
            return op[2]
        parent = span_at(tasks.get(where, []), t)
        return None if parent is None else owner(parent[2], depth + 1)

    core_ns = collections.Counter()
    for spans in ops.values():
        for start, end, op in spans:
            core_ns[op] += end - start
    for where, spans in tasks.items():
        own = ops.get(where, [])
        for start, end, task_id in spans:
            i = bisect.bisect_left(own, (start, 0))
            inside = 0
            while i < len(own) and own[i][0] < end:
                inside += min(own[i][1], end) - max(own[i][0], start)
                i += 1
            core_ns[owner(task_id)] += (end - start) - inside
    return core_ns


def bench_train_profile(town, repeats):
    """Per-op profile of the training step at the first ``--train_sizes`` entry (jax.profiler): core-ms
    per step of each op (``_op_core_ns``), summed by part (PROFILE_PARTS), and the slowest kinds of op; beside
    the peer's (``experiments/torch_profile.py``, torch.profiler) split into the same parts. Tracing
    slows a step (``step_s_traced``), so compare shares, and ``train`` for the step's time."""
    b, t, r = _size(FLAGS.train_sizes[0])
    cfg = _paper_config(b, t, r)
    _, run, compiled = _train_step_runner(cfg, batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg))
    parts = _op_parts(compiled.as_text())
    jax.block_until_ready(run())  # warm-up
    with tempfile.TemporaryDirectory() as trace_dir:
        jax.profiler.start_trace(trace_dir)
        start = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(run())
        step_s = (time.perf_counter() - start) / repeats
        jax.profiler.stop_trace()
        (trace,) = glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True)
        core_ns = _op_core_ns(jax.profiler.ProfileData.from_file(trace))
    part_ns, kind_ns = collections.Counter(), collections.Counter()
    for op, ns in core_ns.items():
        part = "pool tasks of no op" if op is None else parts.get(op, "other programs")
        part_ns[part] += ns
        kind_ns[(part, re.sub(r"\.\d+$", "", op or ""))] += ns  # fusion.12 and fusion.31 are one kind
    ms = lambda ns: ns / 1e6 / repeats
    figure = {
        "batch": b,
        "seq_len": t,
        "image_size": r,
        "step_s_traced": step_s,
        "part_core_ms": {part: ms(ns) for part, ns in part_ns.most_common()},
        "top_op_kinds": [[part, kind, ms(ns)] for (part, kind), ns in kind_ns.most_common(25)],
    }
    peer = _run_peer(
        os.path.join(_REPO, "experiments", "torch_profile.py"),
        "--peer",
        PEER_SCRIPT,
        "--batch",
        b,
        "--seq-len",
        t,
        "--image-size",
        r,
        "--steps",
        repeats,
    )
    if peer is not None:
        figure.update(
            peer_step_s_traced=peer["step_s_median"], peer_part_ms=peer["part_ms"], peer_top_ops=peer["top_ops"]
        )
    return figure


def bench_deconv(town, repeats):
    """Per-layer profile of the decoders' stride-2 transposed convolutions: the sub-pixel reformulation
    (``model.Deconv2x``), flax's plain ``nn.ConvTranspose`` with the same parameters and, with
    ``--peer_python``, eager PyTorch's ``ConvTranspose2d`` (``experiments/torch_layers.py``): forward +
    backward (gradient wrt input and kernel) of each layer of one image decoder at the first
    ``--train_sizes`` entry, paper widths, N = B (T + 1) images."""
    del town
    b, t, r = _size(FLAGS.train_sizes[0])
    cfg = _paper_config(b, t, r)
    widths = model_lib.conv_widths(cfg.model, r)
    n = b * (t + 1)
    # (input side, C in, C out, kernel) of each Deconv2x of one image decoder, as Trunk + ImageDecoder build them
    ins = (cfg.model.feature_dim,) + tuple(reversed(widths[:-1]))
    layers = [(4 * 2**i, c_in, c_out, 3) for i, (c_in, c_out) in enumerate(zip(ins, ins[1:]))]
    layers.append((r // 2, widths[0], 3, 5))
    figure = {
        "batch": b,
        "seq_len": t,
        "image_size": r,
        "layers": [list(layer) for layer in layers],
        "subpixel_layer_s": [],
        "plain_layer_s": [],
    }
    for side, c_in, c_out, k in layers:
        x = jax.random.normal(jax.random.PRNGKey(0), (n, side, side, c_in))
        lo = k - 1 - k // 2
        subpixel = model_lib.Deconv2x(c_out, k)
        plain = nn.ConvTranspose(c_out, (k, k), strides=(2, 2), padding=((lo, lo + 1),) * 2)
        params = subpixel.init(jax.random.PRNGKey(1), x)
        for name, module in (("subpixel", subpixel), ("plain", plain)):
            grad = jax.jit(jax.grad(lambda p, x: jnp.sum(module.apply(p, x) ** 2), argnums=(0, 1)))
            figure[f"{name}_layer_s"].append(_median_s(lambda: grad(params, x), repeats))
    figure.update(subpixel_s=sum(figure["subpixel_layer_s"]), plain_s=sum(figure["plain_layer_s"]))
    figure["plain_over_subpixel"] = figure["plain_s"] / figure["subpixel_s"]
    peer = _run_peer(
        os.path.join(_REPO, "experiments", "torch_layers.py"),
        "--repeats",
        repeats,
        "--layers",
        json.dumps([[n, *layer] for layer in layers]),
    )
    if peer is not None:
        figure.update(torch_layer_s=peer["layer_s"], torch_s=sum(peer["layer_s"]), torch_threads=peer["threads"])
        figure["subpixel_over_torch"] = figure["subpixel_s"] / figure["torch_s"]
    return figure


def bench_infer(town, repeats):
    """One filtering step plus every decoder, paper config at R = 128: latency at batch 1, throughput at
    ``--infer_batch``."""
    cfg = _paper_config(1, 10, 128)
    params = model_lib.init_params(jax.random.PRNGKey(0), cfg)

    @jax.jit
    def infer(params, state, camera, lidar, prev_action):
        state, out = model_lib.filter_step(params, state, camera, lidar, prev_action, None, cfg)
        return state, model_lib.decode(params, jnp.concatenate([out["z1"], out["z2"]], -1), cfg)

    figure = {"image_size": 128}
    for n in (1, FLAGS.infer_batch):
        image = jnp.asarray(np.random.default_rng(0).integers(0, 256, (n, 128, 128, 3), np.uint8))
        state = model_lib.init_filter_state(n, cfg)
        step_s = _median_s(lambda: infer(params, state, image, image, jnp.zeros((n, 2))), repeats)
        if n == 1:
            figure["latency_ms_batch1"] = 1e3 * step_s
        else:
            figure.update(batch=n, frames_per_s=n / step_s)
    return figure


def bench_compile(town, repeats):
    """Compile time of the training step at the paper config (B = 8, R = 128) for several T."""
    del repeats
    figure = {"batch": 8, "image_size": 128}
    for t in FLAGS.compile_seq_lens:
        cfg = _paper_config(8, int(t), 128)
        state = jax.eval_shape(lambda: train_lib.init_state(cfg))
        batch = jax.eval_shape(lambda: batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg))
        step_fn = train_lib.make_train_step(cfg, train_lib.make_mesh())
        start = time.perf_counter()
        step_fn.lower(state, {k: batch[k] for k in train_lib.loss_lib.BATCH_KEYS}, jax.random.PRNGKey(0)).compile()
        figure[f"compile_s_T{t}"] = time.perf_counter() - start
    return figure


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


def _rss_mib(pid):
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024


def bench_memory(town, repeats):
    """Resident memory of ``experiments/train.py --config=cpu`` (a subprocess, sampled every second):
    the peak, and the mean over each quarter of the run after compilation, which should stay flat."""
    del town, repeats
    with tempfile.TemporaryDirectory() as workdir:
        cmd = [
            sys.executable,
            os.path.join(_REPO, "experiments", "train.py"),
            "--config=cpu",
            f"--workdir={workdir}",
            f"--train.num_steps={FLAGS.memory_steps}",
        ]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        samples = []  # (seconds since start, RSS MiB)
        start = time.perf_counter()
        while proc.poll() is None:
            try:
                samples.append((time.perf_counter() - start, _rss_mib(proc.pid)))
            except (FileNotFoundError, StopIteration):  # exiting
                break
            time.sleep(1.0)
        if proc.wait() != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed with exit code {proc.returncode}")
    rss = np.array([m for _, m in samples])
    steady = np.array_split(rss[len(rss) // 5 :], 4)  # skip start-up and compilation (the first fifth)
    return {
        "config": "cpu",
        "train_steps": FLAGS.memory_steps,
        "wall_s": samples[-1][0],
        "peak_rss_mib": float(rss.max()),
        "quarter_mean_rss_mib": [float(q.mean()) for q in steady],
    }


def main(argv):
    del argv
    unknown = sorted(set(FLAGS.what) - set(BENCHMARKS))
    if unknown:
        sys.exit(f"error: --what={','.join(FLAGS.what)}: unknown {unknown}; choose from {BENCHMARKS}")
    if FLAGS.repeats < 1:
        sys.exit(f"error: --repeats={FLAGS.repeats}: must be >= 1")
    if FLAGS.peer_rounds < 1:
        sys.exit(f"error: --peer_rounds={FLAGS.peer_rounds}: must be >= 1")
    if FLAGS.batches_per_drive is not None and FLAGS.batches_per_drive < 1:
        sys.exit(f"error: --batches_per_drive={FLAGS.batches_per_drive}: must be >= 1")
    try:
        for spec in FLAGS.train_sizes:
            _size(spec)
        if not all(p.isdigit() and int(p) > 0 for p in FLAGS.place_frames):
            raise ValueError(f"--place_frames={','.join(FLAGS.place_frames)}: expected positive integers")
    except ValueError as e:
        sys.exit(f"error: {e}")
    os.makedirs(FLAGS.out_dir, exist_ok=True)
    if FLAGS.keep_freed_buffers:
        allocator.keep_freed_buffers()
    if FLAGS.eigen_convolutions:
        xla_cpu.prefer_eigen_convolutions()
    context = {
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": jax.device_count(),
        "cpu_count": os.cpu_count(),
        "convolution_path": xla_cpu.convolution_path(),
    }
    town = build_town(config_lib.DEFAULT_TOWN_SEED)
    results = {}
    for name in FLAGS.what:
        figure = {"benchmark": name, **globals()[f"bench_{name}"](town, FLAGS.repeats), **context}
        results[name] = figure
        print(json.dumps(figure), flush=True)
        with open(os.path.join(FLAGS.out_dir, f"{name}.json"), "w") as f:
            json.dump(figure, f, indent=2)
    print("\n| benchmark | figure | value |\n|---|---|---|")
    for name, figure in results.items():
        rows = figure.get("sizes", [figure])
        for row in rows:
            label = "x".join(str(row[k]) for k in ("batch", "seq_len", "image_size") if k in row)
            label += f" ({row['network']})" if "network" in row else ""
            for key, value in row.items():
                if isinstance(value, float):
                    print(f"| {name} {label} | {key} | {value:.4g} |")
                elif isinstance(value, list) and all(isinstance(v, float) for v in value):
                    print(f"| {name} {label} | {key} | {', '.join(f'{v:.4g}' for v in value)} |")


if __name__ == "__main__":
    app.run(main)
