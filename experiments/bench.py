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
peer's; ``latent`` is each latent's training step (the vector and the bird-eye grid, at each
``--grid_cells``) beside the peer, and ``infer`` each latent's filtering step. ``--noeigen_convolutions``
measures XLA's default convolution path instead of the launchers'.

The benchmarks live in ``experiments/benchmarks/``, one module per family; this file holds their list
(BENCHMARKS), every flag and its check, and the run.
"""

import json
import os
import sys

import jax
from absl import app, flags
from benchmarks import common, data, inference, training

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import launch, xla_cpu
from e2e_percep_jax.sim.town import build_town

# Every benchmark by name, in the order of a run without --what (``train`` before ``train_profile``: the
# step compiles once per process, and ``train`` reports that compile time).
BENCHMARKS = {
    "world": data.bench_world,
    "frames": data.bench_frames,
    "frames_parts": data.bench_frames_parts,
    "batch": data.bench_batch,
    "loop": data.bench_loop,
    "train": training.bench_train,
    "latent": training.bench_latent,
    "place": training.bench_place,
    "train_parts": training.bench_train_parts,
    "train_profile": training.bench_train_profile,
    "deconv": training.bench_deconv,
    "infer": inference.bench_infer,
    "compile": training.bench_compile,
    "eval": inference.bench_eval,
    "memory": training.bench_memory,
}

flags.DEFINE_list("what", list(BENCHMARKS), f"benchmarks to run, any of {tuple(BENCHMARKS)}")
flags.DEFINE_string("out_dir", "runs/bench", "one <benchmark>.json per figure goes here")
flags.DEFINE_integer(
    "repeats", 5, "timed runs per figure, at least (short figures get more, to fill 1 s); the median is reported"
)
flags.DEFINE_list("train_sizes", ["8x10x64", "4x10x128"], "BxTxR of the training-step figures")
flags.DEFINE_integer("peer_rounds", 3, "train: rounds of (ours, the peer) alternated, each of --repeats steps")
flags.DEFINE_string(
    "peer_python",
    os.path.join(common.REPO, ".venv-peer", "bin", "python"),
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
flags.DEFINE_list(
    "grid_cells", ["16"], "latent, infer: the bird-eye grid's cells a side (--model.grid_cells) of its figures"
)
flags.DEFINE_list(
    "grid_warps", ["bilinear"], "latent, infer: how the bird-eye grid is carried (--model.grid_warp) in its figures"
)
flags.DEFINE_list(
    "grid_motions",
    ["ego"],
    "latent, infer: what carries the bird-eye grid's content (--model.grid_motion) in its figures",
)
flags.DEFINE_list(
    "grid_memory_channels",
    ["0"],
    "latent, infer: the bird-eye grid's deterministic memory channels per cell (--model.grid_memory_channels)",
)
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


def main(argv):
    del argv
    unknown = sorted(set(FLAGS.what) - set(BENCHMARKS))
    if unknown:
        sys.exit(f"error: --what={','.join(FLAGS.what)}: unknown {unknown}; choose from {tuple(BENCHMARKS)}")
    if FLAGS.repeats < 1:
        sys.exit(f"error: --repeats={FLAGS.repeats}: must be >= 1")
    if FLAGS.peer_rounds < 1:
        sys.exit(f"error: --peer_rounds={FLAGS.peer_rounds}: must be >= 1")
    if FLAGS.batches_per_drive is not None and FLAGS.batches_per_drive < 1:
        sys.exit(f"error: --batches_per_drive={FLAGS.batches_per_drive}: must be >= 1")
    try:
        for spec in FLAGS.train_sizes:
            common.train_size(spec)
        if not all(p.isdigit() and int(p) > 0 for p in FLAGS.place_frames):
            raise ValueError(f"--place_frames={','.join(FLAGS.place_frames)}: expected positive integers")
        if not all(c.isdigit() for c in FLAGS.grid_cells):
            raise ValueError(f"--grid_cells={','.join(FLAGS.grid_cells)}: expected positive integers")
        if not all(d.isdigit() for d in FLAGS.grid_memory_channels):
            raise ValueError(
                f"--grid_memory_channels={','.join(FLAGS.grid_memory_channels)}: expected non-negative integers"
            )
        for flag, allowed in (("grid_warps", config_lib.GRID_WARPS), ("grid_motions", config_lib.GRID_MOTIONS)):
            if unknown := sorted(set(FLAGS[flag].value) - set(allowed)):
                raise ValueError(f"--{flag}={','.join(FLAGS[flag].value)}: unknown {unknown}; choose from {allowed}")
        for cells in FLAGS.grid_cells:  # valid at both networks' sizes: the cpu preset's R (64) is the smaller
            grid = dict(latent="bev", grid_cells=int(cells))
            try:
                config_lib.validate(config_lib.replace(config_lib.get_config("cpu"), model=grid))
            except ValueError as e:
                raise ValueError(f"--grid_cells={','.join(FLAGS.grid_cells)}: {e}") from None
    except ValueError as e:
        sys.exit(f"error: {e}")
    os.makedirs(FLAGS.out_dir, exist_ok=True)
    launch.process_settings(keep_freed_buffers=FLAGS.keep_freed_buffers, eigen_convolutions=FLAGS.eigen_convolutions)
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
        figure = {"benchmark": name, **BENCHMARKS[name](town, FLAGS.repeats), **context}
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
