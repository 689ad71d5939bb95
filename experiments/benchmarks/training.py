"""The training step's benchmarks: its speed beside the eager PyTorch peer (``../shared/peer/torch_peer_bench.py``,
run by ``--peer_python``), with and without the place stream, where its time goes (by part, by op, in the
decoders' layers), its compile time, and a training run's resident memory."""

import glob
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import flags
from flax import linen as nn

from e2e_percep_jax import allocator, trace_attribution
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax import train as train_lib
from e2e_percep_jax.sim import batch as batch_lib

from .common import REPO, cpu_stream_config, latent_models, median_s, paper_config, train_size, train_step_runner

FLAGS = flags.FLAGS
PEER_SCRIPT = os.path.join(REPO, "..", "shared", "peer", "torch_peer_bench.py")


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
        b, t, r = train_size(size)
        cfg = paper_config(b, t, r)
        compile_s, run, _ = train_step_runner(cfg, batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg))
        ours_s, peers = [], []
        for _ in range(FLAGS.peer_rounds):
            ours_s.append(median_s(run, repeats))
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


def bench_latent(town, repeats):
    """Each latent's training step (:func:`latent_models`) at the ``cpu`` preset's (B, T, R), with the
    preset's network and with the paper's widths, alternated with the eager PyTorch peer (the paper's
    vector-latent network at the same size) for ``--peer_rounds`` rounds of ``repeats`` steps, so that every
    ratio is taken in one window of this shared VM; each figure is the median of its rounds' medians."""
    cpu = config_lib.get_config("cpu")
    b, t, r = cpu.data.batch_size, cpu.data.seq_len, cpu.data.image_size
    runs = {}
    for network, base in (
        ("cpu", config_lib.replace(cpu, data=dict(place_frames=0))),
        ("paper widths", paper_config(b, t, r)),
    ):
        for latent, cfg in latent_models(base).items():
            runs[network, latent] = train_step_runner(cfg, batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg))
    rounds, peers = {key: [] for key in runs}, []
    for _ in range(FLAGS.peer_rounds):
        for key, (_, run, _) in runs.items():
            rounds[key].append(median_s(run, repeats))
        peers.append(_peer(b, t, r, repeats))
    peer_s = None if peers[0] is None else statistics.median(peer["step_s_median"] for peer in peers)
    figures = []
    for (network, latent), step_rounds in rounds.items():
        step_s, vector_s = statistics.median(step_rounds), statistics.median(rounds[network, "vector"])
        figure = {
            "batch": b,
            "seq_len": t,
            "image_size": r,
            "network": f"{network}, {latent}",
            "compile_s": runs[network, latent][0],
            "step_s_median": step_s,
            "step_s_rounds": step_rounds,
            "ratio_vs_vector": step_s / vector_s,
        }
        if peer_s is not None:
            figure.update(peer_step_s_median=peer_s, ratio_vs_peer=peer_s / step_s)
        figures.append(figure)
    return {"sizes": figures}


def bench_place(town, repeats):
    """The place stream's cost: seconds per training step (batch, sharding and step, dispatched as
    ``train.train`` does, over the preset's stream) without it and with each ``--place_frames`` P, for the
    ``cpu`` preset's network and for the paper's widths at the ``cpu`` preset's (B, T, R), the latter
    alternated with the eager PyTorch peer (the same network, no place stream) for ``--peer_rounds``
    rounds, so that each ratio is taken in one window of this shared VM."""
    cpu = cpu_stream_config()
    b, t, r = cpu.data.batch_size, cpu.data.seq_len, cpu.data.image_size
    paper = config_lib.replace(paper_config(b, t, r), data=dict(batches_per_drive=cpu.data.batches_per_drive))
    mesh, sizes = train_lib.make_mesh(), [0, *map(int, FLAGS.place_frames)]
    figures = []
    for name, base in (("cpu", cpu), ("paper widths", paper)):
        runners = {}
        for p in sizes:
            cfg = config_lib.replace(base, data=dict(place_frames=p))
            stream = batch_lib.batch_stream(town, cfg, seed=0)
            runners[p] = (train_step_runner(cfg, next(stream)[1])[1], stream, cfg)

        def run(p):
            step, stream, cfg = runners[p]
            return median_s(lambda: step(train_lib.shard_batch(next(stream)[1], mesh, cfg)), repeats)

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
    b, t, r = train_size(FLAGS.train_sizes[0])
    cfg = paper_config(b, t, r)
    params = model_lib.init_params(jax.random.PRNGKey(0), cfg)
    batch = batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg)
    key = jax.random.PRNGKey(1)
    total = lambda tree: sum(jnp.sum(x) for x in jax.tree.leaves(tree))
    m, n = cfg.model, b * (t + 1)
    filtered = {
        "z1": jnp.zeros((n, m.z1_dim)),
        "z2": jnp.zeros((n, m.z2_dim)),
        "features": jnp.zeros((n, 2 * m.feature_dim)),
    }
    parts = {
        "loss": lambda p: train_lib.loss_lib.loss_fn(p, batch, key, cfg)[0],
        "encoders_and_scan": lambda p: total(
            model_lib.filter_sequence(p, batch["camera"], batch["lidar"], batch["action"], key, cfg)
        ),
        "decoders": lambda p: total(model_lib.decode(p, filtered, cfg)),
    }
    figure = {"batch": b, "seq_len": t, "image_size": r}
    for name, fn in parts.items():
        grad = jax.jit(jax.grad(fn))
        figure[f"{name}_s"] = median_s(lambda: grad(params), repeats)
    return figure


def bench_train_profile(town, repeats):
    """Per-op profile of the training step at the first ``--train_sizes`` entry (jax.profiler): core-ms
    per step of each op, summed by part, and the slowest kinds of op (``e2e_percep_jax/trace_attribution.py``);
    beside the peer's (``experiments/torch_profile.py``, torch.profiler) split into the same parts. Tracing
    slows a step (``step_s_traced``), so compare shares, and ``train`` for the step's time."""
    b, t, r = train_size(FLAGS.train_sizes[0])
    cfg = paper_config(b, t, r)
    _, run, compiled = train_step_runner(cfg, batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg))
    parts = trace_attribution.op_parts(compiled.as_text())
    jax.block_until_ready(run())  # warm-up
    with tempfile.TemporaryDirectory() as trace_dir:
        jax.profiler.start_trace(trace_dir)
        start = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(run())
        step_s = (time.perf_counter() - start) / repeats
        jax.profiler.stop_trace()
        (trace,) = glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True)
        core_ns = trace_attribution.op_core_ns(jax.profiler.ProfileData.from_file(trace))
    part_ns, kind_ns = trace_attribution.core_ns_by_part(core_ns, parts)
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
        os.path.join(REPO, "experiments", "torch_profile.py"),
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
    b, t, r = train_size(FLAGS.train_sizes[0])
    cfg = paper_config(b, t, r)
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
            figure[f"{name}_layer_s"].append(median_s(lambda: grad(params, x), repeats))
    figure.update(subpixel_s=sum(figure["subpixel_layer_s"]), plain_s=sum(figure["plain_layer_s"]))
    figure["plain_over_subpixel"] = figure["plain_s"] / figure["subpixel_s"]
    peer = _run_peer(
        os.path.join(REPO, "experiments", "torch_layers.py"),
        "--repeats",
        repeats,
        "--layers",
        json.dumps([[n, *layer] for layer in layers]),
    )
    if peer is not None:
        figure.update(torch_layer_s=peer["layer_s"], torch_s=sum(peer["layer_s"]), torch_threads=peer["threads"])
        figure["subpixel_over_torch"] = figure["subpixel_s"] / figure["torch_s"]
    return figure


def bench_compile(town, repeats):
    """Compile time of the training step at the paper config (B = 8, R = 128) for several T."""
    del repeats
    figure = {"batch": 8, "image_size": 128}
    for t in FLAGS.compile_seq_lens:
        cfg = paper_config(8, int(t), 128)
        state = jax.eval_shape(lambda: train_lib.init_state(cfg))
        batch = jax.eval_shape(lambda: batch_lib.make_batch(jax.random.PRNGKey(0), town, cfg))
        step_fn = train_lib.make_train_step(cfg, train_lib.make_mesh())
        start = time.perf_counter()
        step_fn.lower(state, {k: batch[k] for k in train_lib.loss_lib.BATCH_KEYS}, jax.random.PRNGKey(0)).compile()
        figure[f"compile_s_T{t}"] = time.perf_counter() - start
    return figure


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
            os.path.join(REPO, "experiments", "train.py"),
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
