"""Where a compiled training step's time goes: each op of its program put in a part of the model by its HLO
metadata, and each op's core time read off an XLA:CPU trace (``jax.profiler``), thread-pool work included.

``experiments/bench.py --what=train_profile`` traces the step and sums the ops' time by part
(:func:`core_ns_by_part`). The parts are named by this package's jit and flax scopes (:data:`PROFILE_PARTS`),
so they live beside the model rather than in the benchmark. Pure functions of the HLO text and the trace:
no JAX computation, no files.
"""

import bisect
import collections
import math
import re

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


def op_parts(hlo_text):
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


def op_core_ns(profile):
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


def core_ns_by_part(core_ns, parts):
    """(Counter {part: core-ns}, Counter {(part, kind of op): core-ns}) of :func:`op_core_ns`'s figures,
    with :func:`op_parts`' ``parts`` of the traced program: ops of other programs and pool tasks of no op
    get parts of their own, and a kind is an op's name less its number (fusion.12 and fusion.31 are one)."""
    part_ns, kind_ns = collections.Counter(), collections.Counter()
    for op, ns in core_ns.items():
        part = "pool tasks of no op" if op is None else parts.get(op, "other programs")
        part_ns[part] += ns
        kind_ns[(part, re.sub(r"\.\d+$", "", op or ""))] += ns
    return part_ns, kind_ns
