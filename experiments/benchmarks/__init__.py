"""The benchmarks that ``experiments/bench.py`` runs, by family: ``data`` (world steps, frames, batches),
``training`` (the training step beside the eager PyTorch peer, its parts and profile, compile time,
memory), ``inference`` (one filtering step, the whole online evaluation); ``common``: what they share.

Each benchmark is a function ``bench_<name>(town, repeats)`` returning its figure as a dict; it reads its
settings from the flags that ``experiments/bench.py`` defines and checks.
"""
