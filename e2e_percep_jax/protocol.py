"""The evaluation protocol as one value: which town, from which start, in which car, over which drives.

A run is trained under one config (its ``config.json``); an evaluation may change what the evaluation
launchers let it change (:data:`EVALUATION_FIELDS`). :func:`of` turns the pair into a :class:`Protocol`:

- ``town_seed`` and ``training_town``: a town the run was not trained in is a held-out town;
- ``known_start``: the pose belief starts at each drive's true first pose (an odometry) or knows nothing;
- ``changes``: every other evaluation field that differs from the run's own, as (field, value) pairs in a
  fixed order: another car (the plant's ``world.ego_*``), other drives (``eval.seed``, ``eval.num_worlds``,
  the detection drives), another reading of the boxes (``eval.score_threshold``, ``eval.nms_iou``, ...) or
  of the belief (``model.pose_filter``);
- the drive set itself (``drives``: the pose drives and detection's), as the evaluation ran it.

Its :attr:`Protocol.name` is the evaluation's directory in the run (``eval``, ``eval_town7_known_start``,
``eval_ego_steer_offset_deg0.5``): two protocols never share a directory, so an evaluation in another car
does not overwrite the run's own. ``metrics.json`` records it (:meth:`Protocol.to_dict`), and the sweep and
the tables read it from there (:func:`from_metrics`), not from directory names.
"""

import dataclasses
import os

from e2e_percep_jax import config as config_lib
from e2e_percep_jax.config import Config

# The evaluation's drive set (EvalConfig fields)
DRIVE_FIELDS = ("num_frames", "num_worlds", "seed", "detection_drives", "detection_frames", "detection_pool")
# What an evaluation may change from the run's config, in the order a protocol's name spells the changes.
# (eval.chunk_steps changes only the memory an evaluation holds; town_seed and known_start are named apart.)
EVALUATION_FIELDS = (
    *(("world", name) for name in config_lib.PLANT_FIELDS),
    *(("eval", name) for name in DRIVE_FIELDS),
    ("eval", "score_threshold"),
    *(("eval", name) for name in ("top_k", "score_floor", "nms_iou", "nms_merge_iou")),
    ("model", "pose_filter"),
)


@dataclasses.dataclass(frozen=True)
class Protocol:
    town_seed: int
    training_town: int
    known_start: bool
    changes: tuple = ()  # ((field name, value), ...): EVALUATION_FIELDS that differ from the run's config
    drives: tuple = ()  # ((DRIVE_FIELDS name, value), ...) of the evaluation

    @property
    def held_out(self) -> bool:
        """Whether the town is one the run was not trained in."""
        return self.town_seed != self.training_town

    @property
    def name(self) -> str:
        """The evaluation's directory name: ``eval``, then ``_town<seed>`` for a held-out town,
        ``_known_start``, ``_no_pose_filter`` for the belief read without its filter, and ``_<field><value>``
        for every other change."""
        name = "eval" + (f"_town{self.town_seed}" if self.held_out else "") + ("_known_start" * self.known_start)
        for field, value in self.changes:
            name += "_no_pose_filter" if field == "pose_filter" else f"_{field}{_spelled(value)}"
        return name

    def to_dict(self) -> dict:
        return dict(dataclasses.asdict(self), name=self.name, held_out=self.held_out)


def _spelled(value) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def of(cfg: Config, trained: Config | None = None) -> Protocol:
    """The protocol of evaluating under ``cfg`` a run trained under ``trained`` (default: ``cfg`` itself, a
    run evaluated as it was configured)."""
    trained = trained or cfg
    value = lambda c, section, name: getattr(getattr(c, section), name)
    # The belief read without its filter is a change whatever the run was trained with: the filter is
    # inference alone, and only the belief head has one.
    trained = config_lib.replace(trained, model=dict(pose_filter="histogram"))
    changes = tuple(
        (name, value(cfg, section, name))
        for section, name in EVALUATION_FIELDS
        if value(cfg, section, name) != value(trained, section, name)
        and not (name == "pose_filter" and cfg.model.pose_head != "belief")
    )
    return Protocol(
        town_seed=cfg.eval.town_seed,
        training_town=cfg.world.town_seed,
        known_start=cfg.eval.known_start,
        changes=changes,
        drives=tuple((name, getattr(cfg.eval, name)) for name in DRIVE_FIELDS),
    )


def of_run(run: str | None, cfg: Config) -> Protocol:
    """:func:`of` ``cfg`` against the config saved in the run directory ``run`` (``config.json``); against
    ``cfg`` itself where there is none yet (a run still to train, a baseline that trains nothing)."""
    saved = run is not None and os.path.exists(os.path.join(run, "config.json"))
    return of(cfg, config_lib.run_config(run) if saved else None)


def from_metrics(metrics: dict, name: str) -> Protocol:
    """The protocol an evaluation's ``metrics.json`` records; one written before it recorded any is read
    from its config (the town, the start) and ``name``, its directory's name (the rest of the changes)."""
    saved = metrics.get("protocol")
    if saved is not None:
        fields = {f.name for f in dataclasses.fields(Protocol)}
        tuples = lambda v: tuple(map(tuple, v)) if isinstance(v, list) else v
        return Protocol(**{k: tuples(v) for k, v in saved.items() if k in fields})
    cfg = Config.from_dict(metrics["config"])
    protocol = of(cfg)
    if protocol.name != name:  # the changes are spelled in the name alone: keep it as a change of its own
        protocol = dataclasses.replace(protocol, changes=(("", name[len(protocol.name) :].lstrip("_")),))
    return protocol
