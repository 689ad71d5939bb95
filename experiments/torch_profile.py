"""Eager PyTorch side of ``bench.py --what=train_profile``: the peer's training step under ``torch.profiler``,
its time split into the same parts as ours.

Run by the peer's python (torch is a benchmark-only tool, never a project dependency):

    .venv-peer/bin/python experiments/torch_profile.py --peer=../shared/peer/torch_peer_bench.py \\
        --batch=8 --seq-len=10 --image-size=64 --steps=5

The step is the peer's own (its ``Model.loss``, backward, Adam) on inputs made as its benchmark makes
them. Forward ops are assigned to a part by the module that runs them (``PARTS``); a backward op to the
part of the forward op it differentiates (autograd's sequence number links them); Adam's ops to
"optimizer"; the rest of the loss's forward and backward to "losses". Prints one JSON line:
{"torch", "threads", "step_s_median", "part_ms": {part: ms per step}, "top_ops": [[part, op, ms per step], ...]}.
"""

import argparse
import collections
import importlib.util
import json
import statistics
import time

import torch
from torch.profiler import ProfilerActivity, profile, record_function

# part -> the peer model's attributes whose forward belongs to it
PARTS = {
    "encoders": ("enc_cam", "enc_lidar"),
    "latent scan": ("p_z2_first", "p_z1", "p_z2", "q_z1_first", "q_z1"),
    "decoders": ("dec", "pixor", "pose"),
}


def load_peer(path):
    spec = importlib.util.spec_from_file_location("torch_peer_bench", path)
    peer = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(peer)
    return peer


def tag_parts(model):
    """Runs each part's modules inside a ``record_function`` range named after the part."""
    for part, names in PARTS.items():
        for name in names:
            module = getattr(model, name)
            for sub in module if isinstance(module, torch.nn.ModuleList) else [module]:
                sub.forward = (lambda forward, part: lambda *a: _in_range(part, forward, *a))(sub.forward, part)


def _in_range(part, fn, *args):
    with record_function(f"part:{part}"):
        return fn(*args)


def part_of(event, forward_part=None):
    """The part of the innermost range around ``event`` (itself included): a part's own range, or, given
    ``forward_part``, a backward node's, which is the part of the forward op it differentiates."""
    while event is not None:
        if event.name.startswith("part:"):
            return event.name[len("part:") :]
        if forward_part is not None and event.name.startswith("autograd::engine::evaluate_function"):
            return forward_part.get(event.sequence_nr)
        event = event.cpu_parent
    return None


def part_of_forward_ops(events):
    """{autograd sequence number: part} of the forward ops run inside a part's range."""
    parts = {}
    for event in events:
        part = part_of(event.cpu_parent)
        if part is not None and event.sequence_nr >= 0:
            parts.setdefault(event.sequence_nr, part)
    return parts


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--peer", required=True, help="path of torch_peer_bench.py")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--seq-len", type=int, default=10)
    ap.add_argument("--image-size", type=int, default=64)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--top", type=int, default=15, help="the slowest ops listed")
    a = ap.parse_args()
    peer = load_peer(a.peer)
    torch.manual_seed(0)
    b, t1, r = a.batch, a.seq_len + 1, a.image_size
    model = peer.Model(r)
    tag_parts(model)
    opt = torch.optim.Adam(model.parameters(), 1e-4)
    g = torch.Generator().manual_seed(1)
    img = lambda c: torch.rand(b, t1, c, r, r, generator=g)
    cam, lidar, road, reg = img(3), img(3), img(3), img(6)
    cls = (torch.rand(b, t1, 1, r, r, generator=g) > 0.95).float()
    pose, actions = torch.randn(b, t1, 5, generator=g), torch.randn(b, t1, 2, generator=g)

    def step():
        opt.zero_grad(set_to_none=True)
        model.loss(cam, lidar, road, cls, reg, pose, actions).backward()
        with record_function("part:optimizer"):
            opt.step()

    step()  # warm-up
    times = []
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(a.steps):
            start = time.perf_counter()
            step()
            times.append(time.perf_counter() - start)
    events = [e for e in prof.events() if not e.name.startswith("part:")]
    forward_part = part_of_forward_ops(events)
    part_us, op_us = collections.Counter(), collections.Counter()
    for event in events:  # self times: each microsecond is counted once, in the innermost op running
        part = part_of(event, forward_part) or "losses"
        part_us[part] += event.self_cpu_time_total
        op_us[(part, event.name)] += event.self_cpu_time_total
    per_step_ms = lambda us: us / 1e3 / a.steps
    print(
        json.dumps(
            {
                "torch": torch.__version__,
                "threads": torch.get_num_threads(),
                "step_s_median": statistics.median(times),
                "part_ms": {part: per_step_ms(us) for part, us in part_us.most_common()},
                "top_ops": [[part, op, per_step_ms(us)] for (part, op), us in op_us.most_common(a.top)],
            }
        )
    )


if __name__ == "__main__":
    main()
