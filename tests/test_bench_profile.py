"""The training step's per-op profile (e2e_percep_jax/trace_attribution.py, behind bench.py
--what=train_profile): ops put in parts by their HLO metadata, and thread-pool tasks given to the op that
started them, on a hand-made trace."""

import jax

from e2e_percep_jax import trace_attribution

_HLO = """
  %conv.1 = f32[8,4,4,16]{3,2,1,0} convolution(%p.1, %w.1), metadata={op_name="jit(step)/jvp(jit(loss_fn))/camera_encoder/Conv_1/conv_general_dilated"}
  %add.2 = f32[16]{0} add(%a.1, %b.1), metadata={op_name="jit(step)/add"}
  ROOT %copy.3 = f32[4,4,8,16]{3,2,1,0} copy(%conv.1)
  %fusion.4 = f32[8,32]{1,0} fusion(%x.1), kind=kLoop, metadata={op_name="jit(step)/jvp(jit(loss_fn))/jit(sequence_loss)/while/body/closed_call/PerceptionModel.decode/x"}
"""

_NAMES = {"op": 1, "record": 2, "start": 3, "stop": 4}
_STATS = {"hlo_op": 1, "_p": 2, "_c": 3}


def _event(kind, start_us, end_us=None, **stats):
    """One XEvent of the text proto: an op (``hlo_op``) or a thread pool's marker (``_p``, ``_c`` ids)."""
    stat = "".join(
        f' stats {{ metadata_id: {_STATS[k]} str_value: "{v}" }}'
        if k == "hlo_op"
        else f" stats {{ metadata_id: {_STATS[k]} int64_value: {v} }}"
        for k, v in stats.items()
    )
    duration_us = 0 if end_us is None else end_us - start_us
    return f"events {{ metadata_id: {_NAMES[kind]} offset_ps: {start_us * 10**6} duration_ps: {duration_us * 10**6}{stat} }}"


def _trace(lines):
    body = "".join(
        f'lines {{ id: {i} name: "t{i}" timestamp_ns: 0 {" ".join(events)} }}\n' for i, events in enumerate(lines)
    )
    names = {
        "op": "an op",
        "record": "ThreadpoolListener::Record",
        "start": "ThreadpoolListener::StartRegion",
        "stop": "ThreadpoolListener::StopRegion",
    }
    meta = "".join(f'event_metadata {{ key: {i} value {{ id: {i} name: "{names[k]}" }} }}\n' for k, i in _NAMES.items())
    meta += "".join(f'stat_metadata {{ key: {i} value {{ id: {i} name: "{k}" }} }}\n' for k, i in _STATS.items())
    return jax.profiler.ProfileData.from_text_proto(f'planes {{ id: 1 name: "/host:CPU" {body} {meta} }}')


def test_ops_are_put_in_parts_by_their_metadata():
    parts = trace_attribution.op_parts(_HLO)
    # The first matching scope wins: the decode inside the scan is the scan's.
    assert parts == {"conv.1": "encoders", "add.2": "optimizer", "copy.3": "made by XLA", "fusion.4": "latent scan"}


def test_pool_tasks_are_given_to_the_op_that_started_them():
    """Hand-computed: conv.1 runs 0-10 us on thread a and starts task 7 (3-13 us on thread b), which starts
    task 8 (11-15 us on a); task 9 has no Record (3 us); task 10 (18-27 us) has no Record and holds
    add.2's own 20-25 us event, so only its other 4 us are a task's."""
    a = [
        _event("op", 0, 10, hlo_op="conv.1"),
        _event("record", 2, _p=7),
        _event("start", 11, _c=8),
        _event("stop", 15),
        _event("start", 18, _c=10),
        _event("op", 20, 25, hlo_op="add.2"),
        _event("stop", 27),
    ]
    b = [
        _event("start", 3, _c=7),
        _event("record", 5, _p=8),
        _event("stop", 13),
        _event("start", 30, _c=9),
        _event("stop", 33),
    ]
    core_ns = trace_attribution.op_core_ns(_trace([a, b]))
    assert core_ns == {"conv.1": (10 + 10 + 4) * 1000, "add.2": 5 * 1000, None: (3 + 4) * 1000}


def test_core_time_is_summed_by_part_and_by_kind_of_op():
    parts = {"conv.1": "encoders", "fusion.2": "encoders", "fusion.3": "encoders", "add.4": "optimizer"}
    core_ns = {"conv.1": 10, "fusion.2": 20, "fusion.3": 30, "add.4": 4, "copy.9": 5, None: 7}
    part_ns, kind_ns = trace_attribution.core_ns_by_part(core_ns, parts)
    # copy.9 is no op of the traced program's text; None is pool time that leads to no op
    assert part_ns == {"encoders": 60, "optimizer": 4, "other programs": 5, "pool tasks of no op": 7}
    assert kind_ns == {
        ("encoders", "conv"): 10,
        ("encoders", "fusion"): 50,
        ("optimizer", "add"): 4,
        ("other programs", "copy"): 5,
        ("pool tasks of no op", ""): 7,
    }
