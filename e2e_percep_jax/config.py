"""Frozen experiment configs, the named presets, validation, and absl flags for every field.

A config is a tree of frozen dataclasses, so it is hashable (usable as a ``jit`` static argument)
and prints itself. Presets:

- ``tiny``:  32x32 images, narrow nets; for tests (seconds per step on 2 CPU cores).
- ``demo``:  the README's main job: trains, evaluates and reports in minutes on this 2-core machine.
- ``cpu``:   the largest config that trains in about an hour on this 2-core machine.
- ``paper``: the paper's network at 128x128 (a GPU job).

Any field is overridden from the command line as ``--<section>.<field>=value`` (for example
``--model.variant=no_roadmap_recon --train.num_steps=500``); see :func:`define_flags`.
"""

import dataclasses
import json
import logging
import math
import os
import sys
import traceback
import warnings
from typing import Any

VARIANTS = ("full", "no_input_recon", "no_roadmap_recon")
# The modular pipeline's methods (e2e_percep_jax.baselines), named here so that launchers check them cheaply.
BASELINES = ("detector", "tracker", "pose", "dead_reckoning", "lidar_odometry", "wheel_odometry")
# belief: a heatmap over the town (pose_belief.py), filtered through motion at evaluation; regression: an MLP
# on the latent sample, smooth-L1 in normalised units (what runs saved before the field was added used);
# reference: the same head on the reference code's objective, 10 x smooth-L1 on raw metres.
POSE_HEADS = ("belief", "regression", "reference")
# How the belief head's frames become a pose (api.Perceiver.step): histogram, the Bayes filter through the
# recorded actions (pose_belief.filter_step); none, each frame's head read alone (the latent's own memory).
POSE_FILTERS = ("histogram", "none")
# What the PIXOR decoder reads: latent, the latent sample z = [z1, z2] alone (the paper); latent_and_features,
# z beside the frame's encoder features [2F], as the belief head reads them (the single-frame detector reads
# the features alone); grid, the bird-eye grid alone (latent "bev"): z is zeroed for it, so the trunk's maps coarser
# than the grid are learned constants (where vehicles stand around the ego) and only the grid's cells say where
# they are now, which the grid keeps where the sensors cannot see.
DETECTION_INPUTS = ("latent", "latent_and_features", "grid")
# The latent: vector, the paper's z1 and z2; bev, the vector beside a stochastic bird-eye grid carried from frame
# to frame, warped by the ego's motion (bev_latent.py), which the PIXOR, lidar and roadmap decoders read. The
# default is bev: it finds the visible vehicles better than the single-frame detector and localises as well
# as the vector at the `cpu` preset (two seeds), and it lifts the `demo` job above the paper at every IoU
# (BUILD_NOTES, "The default latent").
LATENTS = ("vector", "bev")
# How the bird-eye grid's posterior updates a cell: learned, q reads the warped prior and the frame and may write
# anything; lidar_gated, q moves from the prior only as far as the lidar sees the cell (the share of its pixels
# that no nearer return shadows, bev_latent.lidar_visibility), so a cell behind an obstacle keeps its prior, as
# an occupancy grid keeps what it cannot observe; lidar_fused, q is a per-cell observation Gaussian multiplied
# into the prior (a Kalman update), its precision scaled by that same share: a cell the lidar cannot see keeps
# its prior, and a view the network is unsure of (a sliver of a car) moves the cell only as far as it is sure.
GRID_UPDATES = ("learned", "lidar_gated", "lidar_fused")
# What the lidar image's decoder reads (latent "bev"): latent_and_grid, z beside the grid, as the PIXOR and roadmap
# decoders do; latent, z alone, so that the grid answers only to the boxes, the roadmap and its KL. The lidar
# image has no returns from a vehicle the lidar cannot see, so a grid that reconstructs it is taught to erase the
# vehicles an occluder hides, which the boxes ask it to keep (BUILD_NOTES, "A grid that no longer draws the lidar").
LIDAR_DECODER_INPUTS = ("latent_and_grid", "latent")
# How the bird-eye grid is carried to the next frame (latent "bev"): bilinear, sampled where the ego's motion moved
# each cell centre, which blurs what the grid holds every frame the ego moves by a fraction of a cell; lattice, on
# cells kept off the ego's by under half a cell so that a translation moves the grid by whole cells, and the
# decoders read it sampled once onto the ego's cells (bev_latent.warp_on_lattice).
GRID_WARPS = ("bilinear", "lattice")
# What carries the bird-eye grid's content between frames (latent "bev"): ego, the ego's motion alone (the warp
# above), so a vehicle that drives on while hidden leaves the cells that hold it; ego_and_flow, then a learned
# flow per cell (bev_latent.transport), read from the warped grid, so the prior can move a car along its lane;
# ego_and_taught_flow, the same flow learnt from the vehicles' true moves alone (--train.flow_weight), its
# gradient stopped where it carries the grid, as the ego-motion head's is; ego_and_carried_flow, a flow kept in
# the filter's state and carried with the grid (a hidden car keeps its last move), corrected each frame from the
# lidar maps of that frame and the one before, and taught as the last (model.PerceptionModel.grid_step).
GRID_MOTIONS = ("ego", "ego_and_flow", "ego_and_taught_flow", "ego_and_carried_flow")
FLOW_MOTIONS = GRID_MOTIONS[1:]  # the grid motions with a scene flow
TAUGHT_FLOW_MOTIONS = GRID_MOTIONS[2:]  # those whose flow learns from the vehicles' moves alone
DEFAULT_TOWN_SEED = 0


# The ego plant's fields of WorldConfig (world.EgoPlant): all zero is the exact-action world.
PLANT_FIELDS = (
    "ego_lag_s",
    "ego_steer_offset_deg",
    "ego_steer_gain_std",
    "ego_distance_scale_std",
    "ego_understeer_deg_per_g",
    "ego_accel_noise_mps2",
    "ego_curvature_noise_1pm",
)


@dataclasses.dataclass(frozen=True)
class WorldConfig:
    town_seed: int = DEFAULT_TOWN_SEED  # the training town; any other seed is a held-out town
    num_vehicles: int = 100  # surrounding vehicles, the ego not counted
    # The ego car as a plant (world.EgoPlant): its commands do not determine its motion. Magnitudes and
    # their sources: BUILD_NOTES.md, "The ego plant". All zero gives the exact-action world, bit for bit.
    ego_lag_s: float = 0.15  # first-order time constant of the pedal and steering actuators
    ego_steer_offset_deg: float = 0.25  # std over drives of the road-wheel angle's offset
    ego_steer_gain_std: float = 0.03  # std over drives of the steering gain (mean 1)
    ego_distance_scale_std: float = 0.02  # std over drives of the wheels' distance scale (mean 1)
    ego_understeer_deg_per_g: float = 2.0  # road-wheel angle needed per g of lateral acceleration (slip)
    ego_accel_noise_mps2: float = 0.05  # per-step std of the acceleration's noise
    ego_curvature_noise_1pm: float = 0.001  # per-step std of the curvature's noise (heading noise per metre)


@dataclasses.dataclass(frozen=True)
class DataConfig:
    image_size: int = 128  # R: every image is [R, R, 3]; a power of two >= 32
    batch_size: int = 8  # B sequences per training batch
    seq_len: int = 10  # T: each sequence has T+1 frames
    warmup_steps: int = 200  # world steps from reset before a sequence is recorded (steady traffic)
    # K: each drive of B worlds feeds K batches (warm-up paid once per K), each seen by egos handed over
    # to random NPCs, the stream taking its batches from K drives in turn so successive batches still come
    # from different worlds; 1 = every batch from fresh worlds (batch.py). 10 batches a drive cost 6-9 % of
    # a `cpu` step against 20-22 % for fresh worlds, and learned as well over three seeds.
    batches_per_drive: int = 10
    # The place stream: P extra single frames a step, each at a uniformly random point of the town's lanes
    # (batch.place_frames), that train the belief pose head and the encoders through it: many more places
    # a step than the B sequences' few. 0 = none. 32 cost 7-10 % of a step and halved the `cpu` preset's
    # location error at 3,000 steps (two seeds; BUILD_NOTES, "Localisation sooner").
    place_frames: int = 32
    # A memory lever: the share of training sequences in which one vehicle that the lidar sees in the first
    # frame vanishes from every sensor from a random later frame to the last, while the targets keep it
    # (batch.vanishing): a remembered vehicle made on purpose, as 11-frame sequences hold almost none.
    # 0 = the paper.
    vanish_share: float = 0.0
    # Another: the share of training sequences in which a phantom wall slides across the line of sight to
    # one vehicle the lidar sees in the first frame, from a random later frame on, so the beams stop short
    # and the vehicle lies in its shadow while the targets keep it (batch.occluding): an occlusion made as
    # the world makes one, where vanishing lets the beams pass. 0 = the paper.
    occluder_share: float = 0.0
    # Carried state (needs K > 1): no hand-over inside a drive, and the latent filter state at the end of
    # one segment starts the drive's next, gradients cut between them (truncated BPTT over K segments).
    carry_state: bool = False


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    # Conv widths of the encoder's stride-2 layers, deepest last; the first log2(R/4) are used, so at
    # R = 128 these are the paper's (32, 64, 128, 256, 256). Decoders mirror them.
    conv_channels: tuple = (32, 64, 128, 256, 256, 256)
    feature_dim: int = 256  # per-sensor feature (the encoder's last 4x4 VALID conv)
    hidden_dim: int = 256  # width of every latent / pose MLP
    # Width of the belief head's two hidden layers; 0 = hidden_dim. Its output is a logit per cell (about
    # 2,300) and bin: a wider head names places sooner (BUILD_NOTES, "Localisation sooner").
    pose_hidden_dim: int = 512
    z1_dim: int = 32
    z2_dim: int = 256
    variant: str = "full"  # one of VARIANTS
    pose_head: str = "belief"  # one of POSE_HEADS
    pose_cell_m: float = 10.0  # the belief's cell size (metres)
    pose_heading_bins: int = 36  # the belief's heading bins
    # Std of the belief head's Gaussian soft targets, in cells (place) and bins (heading): label smoothing
    pose_target_std_cells: float = 0.5
    pose_filter: str = "histogram"  # one of POSE_FILTERS; inference only, so evaluation may change it
    detection_input: str = "latent"  # one of DETECTION_INPUTS
    latent: str = "bev"  # one of LATENTS
    # The bird-eye grid (latent "bev"): G cells a side over the BEV view (at R 64, 16 cells are 2 m), C channels
    # per cell, each a Gaussian; G is a size the decoders' trunk passes through: a power of two in [4, R / 2].
    grid_cells: int = 16
    grid_channels: int = 8
    # D channels of a deterministic recurrent memory per cell beside the grid's C Gaussians (Dreamer's path,
    # per cell): h_t = GRU(warped h_t-1, warped s_t-1, a_t-1), read by the grid's prior and posterior and by
    # the decoders beside s_t, and carried with it; the frame reaches it only through the ego's motion that
    # warps it. What h holds costs no KL and no sampling noise. 0 = none.
    grid_memory_channels: int = 0
    grid_update: str = "learned"  # one of GRID_UPDATES
    lidar_decoder_input: str = "latent_and_grid"  # one of LIDAR_DECODER_INPUTS
    grid_warp: str = "bilinear"  # one of GRID_WARPS
    grid_motion: str = "ego"  # one of GRID_MOTIONS

    @property
    def histogram_belief(self) -> bool:
        """Whether the pose is the belief head's, filtered by the histogram (what known starts, the lidar
        odometry and the belief's regions need)."""
        return self.pose_head == "belief" and self.pose_filter == "histogram"

    @property
    def carries_flow(self) -> bool:
        """Whether the filter state carries a scene flow and the frame before's lidar map (the grid's
        ``ego_and_carried_flow``)."""
        return self.latent == "bev" and self.grid_motion == "ego_and_carried_flow"


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    seed: int = 0
    num_steps: int = 3000
    # 1e-3, not the reference's 1e-4: reaches 1e-4's 600-step loss in 200 steps
    learning_rate: float = 1e-3
    # The share of num_steps at the end over which the learning rate falls to zero along a cosine; 0 = a
    # constant rate (the reference). A fixed budget's last steps then settle instead of wandering: AP@0.5
    # +2.6-4.7 points and the location error 0.2-0.6 m lower at the `cpu` preset's 3,000 steps (two seeds).
    lr_decay_share: float = 0.3
    # Global gradient-norm clip before Adam; 0 = none (the reference). One step whose KL spikes (a prior
    # scale at its 1e-5 floor) otherwise fills Adam's second moment for thousands of steps. 1e6 lies above
    # the steady norms (3e4-6e5), below a spike's (1e13).
    max_grad_norm: float = 1e6
    # The reference averages the ELBO over its batch but SUMS the detection and pose losses over it (the
    # paper's B = 32). Per sequence (loss.py's normalisation, whatever B is) that is perception x 32.
    perception_weight: float = 32.0
    # A further factor on the pose term alone (its weight: perception_weight * pose_weight). 1 = the
    # reference. Larger asks the latent to carry place, which it otherwise barely holds: with 16 and the
    # 512-wide belief head both `cpu` seeds were within 5 m and 0.07 rad by 2,000 steps, where pose weight 4
    # and a 128-wide head were at 10-16 m (BUILD_NOTES, "The `cpu` preset with both levers").
    pose_weight: float = 16.0
    # beta on the z1 KL (beta-VAE). 1 = the reference's ELBO; < 1 lets the latent hold more of what the
    # heads need (place, above all) at the price of a looser bound.
    kl_weight: float = 1.0
    # A memory lever: the share of frames (never a sequence's first) whose observation the latent filter does
    # not see in training: there the posterior is the prior (z1, and the bird-eye grid), so the latent must
    # carry the scene through them, while every decoder is still scored on them. 0 = the paper.
    observation_drop_share: float = 0.0
    # A memory lever: the share of frames (never a sequence's first) whose lidar image loses one random wedge
    # of returns beyond a random range in training (``loss.lidar_shadows``), as a car hidden behind another
    # loses its returns, while the targets keep every vehicle. The camera is left whole. 0 = the paper.
    lidar_shadow_share: float = 0.0
    # A memory lever: the detection loss's weight on the target pixels of remembered vehicles (seen by a sensor
    # earlier in the sequence, by neither now: ``metrics.box_groups``), every other pixel weighing 1, so that
    # the few hidden cars a batch holds are not drowned by the visible ones. 1 = the paper.
    remembered_weight: float = 1.0
    # A memory lever: the same weight on the target pixels of unseen vehicles (seen by neither sensor in the
    # sequence's last ``metrics.REMEMBER_FRAMES`` frames). At 0 the loss no longer asks the decoder to guess
    # cars it has no evidence of; that does not lift precision (BUILD_NOTES, "Unseen vehicles left out of
    # the detection loss"). 1 = the paper.
    unseen_weight: float = 1.0
    # A memory lever: the same weight on the target pixels of vehicles about to hide: the lidar sees them now
    # and, still in view, no longer does within ``loss.HIDING_FRAMES`` frames of the sequence. Most remembered
    # vehicles are lost in those frames, while a sliver is seen, before memory is asked for (BUILD_NOTES,
    # "Vehicles about to hide weighted in the detection loss"). 1 = the paper.
    hiding_weight: float = 1.0
    # A memory lever, with a scene flow (--model.grid_motion, FLOW_MOTIONS): the weight of its squared error
    # (metres^2, summed over the grid's cells, times perception_weight) against the vehicles' true moves
    # between frames (``bev_latent.vehicle_flow``), so that the flow carries a hidden car along its lane as
    # the ego-motion head carries the grid. 0 = the flow learns from the ELBO alone.
    flow_weight: float = 0.0
    # The weight of the cells a vehicle covers within that error (every other cell 1). Moving cars cover ~1 % of
    # the cells: at 1 the error of a small flow on every empty cell outweighs theirs, and the flow learns to
    # stand still (BUILD_NOTES, "A flow carried as state").
    flow_vehicle_weight: float = 1.0
    checkpoint_every: int = 500  # steps; a checkpoint is also written at exit
    log_every: int = 10
    max_nonfinite_in_a_row: int = 10  # stop after this many skipped (non-finite) updates in a row


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    num_frames: int = 15000  # N frames scored in total, as in the paper's table
    num_worlds: int = 8  # E drives from held-out start keys, N / E frames each
    seed: int = 1000  # evaluation start keys; disjoint from training data keys
    town_seed: int = DEFAULT_TOWN_SEED
    chunk_steps: int = 100  # world steps (warm-up or frames) per scanned chunk; memory is flat in num_frames
    score_threshold: float = 0.5
    # How PIXOR maps become scored boxes (e2e_percep_jax.detection): top_k candidates a frame kept on the
    # device, the lowest score accumulated into the PR curves, the greedy NMS's rotated-IoU threshold (0.1
    # lifts the remembered group's AP: BUILD_NOTES, "A tighter NMS"), and the IoU above which a kept box is
    # merged with those it suppresses (metrics.merging_nms; 1 = none: BUILD_NOTES, "Merging the fan of
    # boxes"). Part of the protocol: a change names its own directory.
    top_k: int = 64
    score_floor: float = 0.05
    nms_iou: float = 0.3
    nms_merge_iou: float = 1.0
    # The pose protocol: False = global (the belief starts uniform over the town); True = known start (the
    # belief starts at each drive's true first pose, then follows the actions alone: odometry).
    known_start: bool = False
    # Detection's drives, beside the pose drives above (which alone give the pose figures): D short drives
    # of detection_frames frames each, chosen from detection_pool candidate drives (held-out keys of their
    # own) as those holding the most remembered boxes (seen by neither sensor now, by one within 3 s): a
    # random draw holds too few of them to measure memory (BUILD_NOTES, "Occluded AP that measures
    # memory"). detection_drives 0: detection is scored on the pose drives; detection_pool 0: no choice,
    # the first D candidates.
    detection_drives: int = 0
    detection_frames: int = 200
    detection_pool: int = 0
    # The lidar odometry's spread (calibration.fit_spread), fitted into the run's motion model the first time
    # a town the place head never saw is evaluated from its known start: spread_drives_per_town drives of
    # spread_frames frames in each of spread_town_seeds (towns that no training batch, place stream or table
    # drives). Not part of the protocol: the fit is kept once made.
    spread_drives_per_town: int = 4
    spread_frames: int = 1500
    spread_town_seeds: tuple = (101, 102, 103, 104)


# (section, old name) -> new name: runs saved before a rename still read back.
RENAMED_FIELDS = {("eval", "num_steps"): "num_frames"}
# (section, field) -> the value a run saved before the field existed ran with, where today's default differs:
# the defaults became the presets' recipe once the fields were there to hold it.
SAVED_WITHOUT = {
    ("data", "batches_per_drive"): 1,
    ("data", "place_frames"): 0,
    ("model", "pose_hidden_dim"): 0,
    ("model", "pose_head"): "regression",
    ("model", "latent"): "vector",
    ("train", "lr_decay_share"): 0.0,
    ("train", "max_grad_norm"): 0.0,
    ("train", "pose_weight"): 1.0,
}


@dataclasses.dataclass(frozen=True)
class Config:
    world: WorldConfig = WorldConfig()
    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    train: TrainConfig = TrainConfig()
    eval: EvalConfig = EvalConfig()

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2)

    @classmethod
    def from_json(cls, text: str) -> "Config":
        """Inverse of :meth:`to_json`; see :meth:`from_dict`."""
        return cls.from_dict(json.loads(text))

    @classmethod
    def from_dict(cls, saved: dict) -> "Config":
        """A config from its saved sections (as ``metrics.json`` holds them): JSON lists become tuples
        again, a field missing (added since it was saved) takes the value runs then ran with
        (``SAVED_WITHOUT``, else its default), a renamed field (``RENAMED_FIELDS``) is read under its new name,
        unknown fields raise ValueError."""
        sections = {}
        for section in dataclasses.fields(cls):
            fields = {RENAMED_FIELDS.get((section.name, k), k): v for k, v in saved.get(section.name, {}).items()}
            missing = {k: v for (s, k), v in SAVED_WITHOUT.items() if s == section.name and k not in fields}
            fields = {**missing, **fields}
            known = {f.name for f in dataclasses.fields(section.default)}
            if set(fields) - known:
                raise ValueError(f"config.json: unknown fields {sorted(set(fields) - known)} in [{section.name}]")
            sections[section.name] = dataclasses.replace(
                section.default, **{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()}
            )
        return cls(**sections)


class MissingRunFileError(FileNotFoundError, ValueError):
    """A training run's file (config.json, a checkpoint) is missing. A ValueError like every other bad input
    of a run directory, and a FileNotFoundError."""


def run_config(workdir: str) -> Config:
    """The config saved in training run ``workdir``; MissingRunFileError or ValueError (one line, naming the
    file) if it is missing or cannot be read."""
    path = os.path.join(workdir, "config.json")
    if not os.path.exists(path):
        raise MissingRunFileError(f"{workdir}: no config.json; is it a training run directory?")
    try:
        with open(path) as f:
            return Config.from_json(f.read())
    except (ValueError, TypeError, AttributeError) as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise ValueError(
            f"{path}: not a config ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
        ) from None


def replace(cfg: Config, **sections: dict) -> Config:
    """``cfg`` with fields replaced per section: ``replace(cfg, data=dict(image_size=64))``."""
    return dataclasses.replace(
        cfg, **{name: dataclasses.replace(getattr(cfg, name), **fields) for name, fields in sections.items()}
    )


_DETECTION_DRIVES = dict(detection_drives=160, detection_frames=200, detection_pool=2048)

# Every preset trains the defaults' recipe (the place stream, the belief head 512 wide, pose weight 16, lr 1e-3
# decaying over the last 30 % and the clip; the reference's lr 1e-4, constant, with no clip) at its own size.
PRESETS = {
    # the paper's network and batch; 10 m belief cells, as measured at this size (5 m not yet); evaluated on the
    # tables' protocol, as the `cpu` rows beside it
    "paper": replace(Config(), data=dict(batch_size=32), eval=dict(**_DETECTION_DRIVES)),
    "cpu": replace(
        Config(),
        data=dict(image_size=64),
        # 5 m belief cells: 2.2 m at 3,000 steps on both seeds, where 10 m cells flatten at 3.4-3.8 m (a point
        # uniform in a 10 m cell lies 3.8 m from its centre); BUILD_NOTES, "Finer belief cells"
        model=dict(conv_channels=(16, 32, 64, 128, 128), feature_dim=128, hidden_dim=128, pose_cell_m=5.0),
        # detection's own drives: 160 of 200 frames chosen of 2,048 for their remembered boxes
        # (BUILD_NOTES, "Occluded AP that measures memory")
        eval=dict(num_frames=15000, **_DETECTION_DRIVES),
    ),
    "demo": replace(
        Config(),
        data=dict(image_size=64),
        # the `cpu` network (at R 64 both use four conv widths) on a shorter budget
        model=dict(conv_channels=(16, 32, 64, 128), feature_dim=128, hidden_dim=128),
        # 1,200 steps: with the clip the network detects from ~800, and boxes fit tightly from ~1,200; the
        # rate decays over the last 360 (both seeds then inside the paper's 7.1 m; BUILD_NOTES, "A learning
        # rate that decays at the end of the budget")
        train=dict(num_steps=1200, checkpoint_every=200),
        # drives of 750 frames: a drive finds its place within its first few hundred frames
        eval=dict(num_frames=3000, num_worlds=4),
    ),
    # the tests' size: fresh worlds for every batch, no place stream, the reference's optimiser, the paper's
    # vector latent (the grid's tests set --model.latent=bev)
    "tiny": replace(
        Config(),
        world=dict(num_vehicles=20),
        data=dict(image_size=32, batch_size=2, seq_len=3, warmup_steps=20, batches_per_drive=1, place_frames=0),
        model=dict(
            conv_channels=(8, 16, 32),
            feature_dim=32,
            hidden_dim=32,
            z1_dim=8,
            z2_dim=16,
            pose_hidden_dim=0,
            latent="vector",
        ),
        train=dict(
            num_steps=20,
            checkpoint_every=10,
            log_every=5,
            learning_rate=1e-4,
            lr_decay_share=0.0,
            max_grad_norm=0.0,
            pose_weight=1.0,
        ),
        # the odometry's spread fitted on one town's drive: the fit builds, drives and matches each of its towns
        eval=dict(
            num_frames=40,
            num_worlds=2,
            chunk_steps=10,
            spread_drives_per_town=1,
            spread_frames=300,
            spread_town_seeds=(101,),
        ),
    ),
}


def get_config(name: str) -> Config:
    if name not in PRESETS:
        raise ValueError(f"--config={name!r} is not a preset; choose one of {sorted(PRESETS)}")
    return PRESETS[name]


def validate(cfg: Config) -> Config:
    """Raises ``ValueError`` naming the offending field (as its flag) if ``cfg`` cannot run."""
    r = cfg.data.image_size
    if r < 32 or r & (r - 1):
        raise ValueError(f"--data.image_size={r}: must be a power of two >= 32")
    n_layers = int(math.log2(r // 4))
    if len(cfg.model.conv_channels) < n_layers:
        raise ValueError(
            f"--model.conv_channels has {len(cfg.model.conv_channels)} widths; image_size {r} needs {n_layers}"
        )
    choices = {
        "variant": VARIANTS,
        "pose_head": POSE_HEADS,
        "pose_filter": POSE_FILTERS,
        "detection_input": DETECTION_INPUTS,
        "latent": LATENTS,
        "grid_update": GRID_UPDATES,
        "lidar_decoder_input": LIDAR_DECODER_INPUTS,
        "grid_warp": GRID_WARPS,
        "grid_motion": GRID_MOTIONS,
    }
    for name, allowed in choices.items():
        if getattr(cfg.model, name) not in allowed:
            raise ValueError(f"--model.{name}={getattr(cfg.model, name)!r}: choose one of {allowed}")
    if cfg.model.detection_input == "grid" and cfg.model.latent != "bev":
        raise ValueError("--model.detection_input=grid reads the bird-eye grid: needs --model.latent=bev")
    g = cfg.model.grid_cells
    if cfg.model.latent == "bev" and (g < 4 or g > r // 2 or g & (g - 1)):
        raise ValueError(f"--model.grid_cells={g}: must be a power of two in [4, data.image_size / 2 = {r // 2}]")
    if cfg.model.latent == "bev" and cfg.model.grid_channels < 1:
        raise ValueError(f"--model.grid_channels={cfg.model.grid_channels}: must be >= 1")
    if cfg.model.grid_memory_channels < 0 or (cfg.model.grid_memory_channels and cfg.model.latent != "bev"):
        raise ValueError(
            f"--model.grid_memory_channels={cfg.model.grid_memory_channels}: must be >= 0, and > 0 only with "
            "--model.latent=bev (it is the bird-eye grid's memory)"
        )
    for name, verb in (("grid_update", "updates"), ("grid_warp", "carries"), ("grid_motion", "carries")):
        value = getattr(cfg.model, name)  # the grid's own fields: any but the default needs the grid
        if value != getattr(ModelConfig, name) and cfg.model.latent != "bev":
            raise ValueError(f"--model.{name}={value!r} {verb} the bird-eye grid: needs --model.latent=bev")
    if cfg.model.lidar_decoder_input != "latent_and_grid" and cfg.model.latent != "bev":
        raise ValueError(
            f"--model.lidar_decoder_input={cfg.model.lidar_decoder_input!r} keeps the bird-eye grid from the lidar "
            "decoder: needs --model.latent=bev"
        )
    # The filter moves a heading bin's mass by at most one cell a step (pose_belief.predict): 2 m is above
    # the world's fastest step (12 m/s x 0.1 s); above 40 m a cell is as large as a block.
    if not 2.0 <= cfg.model.pose_cell_m <= 40.0:
        raise ValueError(f"--model.pose_cell_m={cfg.model.pose_cell_m}: must lie in [2, 40] metres")
    # above 5 cells a target spreads over a block or more: the head would learn no place
    if not 0 < cfg.model.pose_target_std_cells <= 5.0:
        raise ValueError(f"--model.pose_target_std_cells={cfg.model.pose_target_std_cells}: must lie in (0, 5] cells")
    if not 4 <= cfg.model.pose_heading_bins <= 360:
        raise ValueError(f"--model.pose_heading_bins={cfg.model.pose_heading_bins}: must lie in [4, 360]")
    positive = {
        "world.num_vehicles": cfg.world.num_vehicles,
        "data.batch_size": cfg.data.batch_size,
        "data.seq_len": cfg.data.seq_len,
        "data.batches_per_drive": cfg.data.batches_per_drive,
        "model.feature_dim": cfg.model.feature_dim,
        "model.hidden_dim": cfg.model.hidden_dim,
        "model.z1_dim": cfg.model.z1_dim,
        "model.z2_dim": cfg.model.z2_dim,
        "train.num_steps": cfg.train.num_steps,
        "train.learning_rate": cfg.train.learning_rate,
        "train.perception_weight": cfg.train.perception_weight,
        "train.kl_weight": cfg.train.kl_weight,
        "train.remembered_weight": cfg.train.remembered_weight,
        "train.checkpoint_every": cfg.train.checkpoint_every,
        "train.log_every": cfg.train.log_every,
        "train.max_nonfinite_in_a_row": cfg.train.max_nonfinite_in_a_row,
        "eval.num_frames": cfg.eval.num_frames,
        "eval.num_worlds": cfg.eval.num_worlds,
        "eval.chunk_steps": cfg.eval.chunk_steps,
        "eval.detection_frames": cfg.eval.detection_frames,
        "eval.spread_drives_per_town": cfg.eval.spread_drives_per_town,
        "eval.spread_frames": cfg.eval.spread_frames,
    }
    positive.update({f"model.conv_channels[{i}]": c for i, c in enumerate(cfg.model.conv_channels)})
    for name, value in positive.items():
        if not value > 0:
            raise ValueError(f"--{name}={value}: must be positive")
    for name in ("unseen_weight", "hiding_weight", "flow_weight", "flow_vehicle_weight"):
        if not getattr(cfg.train, name) >= 0:
            raise ValueError(f"--train.{name}={getattr(cfg.train, name)}: must be at least 0")
    if cfg.train.flow_weight and (cfg.model.latent != "bev" or cfg.model.grid_motion not in FLOW_MOTIONS):
        raise ValueError(
            f"--train.flow_weight={cfg.train.flow_weight} teaches the grid's scene flow: needs --model.latent=bev "
            f"and --model.grid_motion one of {FLOW_MOTIONS}"
        )
    if cfg.model.grid_motion in TAUGHT_FLOW_MOTIONS and not cfg.train.flow_weight:
        raise ValueError(
            f"--model.grid_motion={cfg.model.grid_motion} learns the flow from the vehicles' moves alone: needs "
            "--train.flow_weight > 0"
        )
    for name in ("observation_drop_share", "lidar_shadow_share"):
        if not 0.0 <= getattr(cfg.train, name) < 1.0:
            raise ValueError(f"--train.{name}={getattr(cfg.train, name)}: must lie in [0, 1)")
    for name in ("vanish_share", "occluder_share"):
        if not 0.0 <= getattr(cfg.data, name) <= 1.0:
            raise ValueError(f"--data.{name}={getattr(cfg.data, name)}: must lie in [0, 1]")
    seeds = {
        "world.town_seed": cfg.world.town_seed,
        "train.seed": cfg.train.seed,
        "eval.seed": cfg.eval.seed,
        "eval.town_seed": cfg.eval.town_seed,
    }
    for name, value in seeds.items():
        if value < 0:
            raise ValueError(f"--{name}={value}: must be >= 0")
    # the spread is fitted on towns neither trained on (their streets hold the odometry tighter) nor evaluated
    spread_towns = cfg.eval.spread_town_seeds
    if not spread_towns or min(spread_towns) < 0 or {cfg.world.town_seed, cfg.eval.town_seed} & set(spread_towns):
        raise ValueError(
            f"--eval.spread_town_seeds={flag_value(spread_towns)}: must name one or more town seeds >= 0, neither "
            f"the training town (--world.town_seed={cfg.world.town_seed}) nor the evaluated one "
            f"(--eval.town_seed={cfg.eval.town_seed})"
        )
    plant_limits = dict(zip(PLANT_FIELDS, (1.0, 5.0, 0.2, 0.2, 10.0, 1.0, 0.05)))
    for name, limit in plant_limits.items():
        value = getattr(cfg.world, name)
        if not 0.0 <= value <= limit:  # (a std at the limit still keeps every drawn gain and scale above 0.5)
            raise ValueError(f"--world.{name}={value}: must lie in [0, {limit:g}] (0: off)")
    if cfg.data.warmup_steps < 0:
        raise ValueError(f"--data.warmup_steps={cfg.data.warmup_steps}: must be >= 0")
    if not cfg.train.pose_weight >= 0:
        raise ValueError(f"--train.pose_weight={cfg.train.pose_weight}: must be >= 0 (0: no pose loss)")
    if not 0.0 <= cfg.train.lr_decay_share < 1.0:
        raise ValueError(f"--train.lr_decay_share={cfg.train.lr_decay_share}: must lie in [0, 1) (0: constant)")
    if not cfg.train.max_grad_norm >= 0:
        raise ValueError(f"--train.max_grad_norm={cfg.train.max_grad_norm}: must be >= 0 (0: no clipping)")
    if cfg.model.pose_hidden_dim < 0:
        raise ValueError(f"--model.pose_hidden_dim={cfg.model.pose_hidden_dim}: must be >= 0 (0: --model.hidden_dim)")
    if cfg.data.place_frames < 0:
        raise ValueError(f"--data.place_frames={cfg.data.place_frames}: must be >= 0 (0: no place stream)")
    if cfg.data.place_frames and cfg.model.pose_head != "belief":
        raise ValueError(
            f"--data.place_frames={cfg.data.place_frames}: trains the belief pose head; "
            f"--model.pose_head={cfg.model.pose_head!r} has none"
        )
    if cfg.data.carry_state and cfg.data.batches_per_drive < 2:
        raise ValueError(
            f"--data.carry_state: needs segments to carry across, --data.batches_per_drive >= 2 "
            f"(got {cfg.data.batches_per_drive})"
        )
    if cfg.eval.known_start and not cfg.model.histogram_belief:
        raise ValueError(
            "--eval.known_start: needs the belief pose head and its filter (--model.pose_head=belief "
            "--model.pose_filter=histogram)"
        )
    if cfg.eval.detection_drives < 0:
        raise ValueError(f"--eval.detection_drives={cfg.eval.detection_drives}: must be >= 0 (0: the pose drives)")
    if cfg.eval.detection_pool and cfg.eval.detection_pool < cfg.eval.detection_drives:
        raise ValueError(
            f"--eval.detection_pool={cfg.eval.detection_pool}: must be 0 (no choice) or at least "
            f"--eval.detection_drives={cfg.eval.detection_drives}"
        )
    if not 0.0 < cfg.eval.score_threshold < 1.0:
        raise ValueError(f"--eval.score_threshold={cfg.eval.score_threshold}: must lie in (0, 1)")
    if cfg.eval.top_k < 1:
        raise ValueError(f"--eval.top_k={cfg.eval.top_k}: must be positive")
    if not 0.0 <= cfg.eval.score_floor < 1.0:
        raise ValueError(f"--eval.score_floor={cfg.eval.score_floor}: must lie in [0, 1)")
    if not 0.0 < cfg.eval.nms_iou <= 1.0:
        raise ValueError(f"--eval.nms_iou={cfg.eval.nms_iou}: must lie in (0, 1]")
    if not cfg.eval.nms_iou <= cfg.eval.nms_merge_iou <= 1.0:
        raise ValueError(
            f"--eval.nms_merge_iou={cfg.eval.nms_merge_iou}: must lie in [--eval.nms_iou={cfg.eval.nms_iou}, 1]"
        )
    return cfg


# ----------------------------------------------------------------------------- command line


def fields():
    """(section, field, default type) for every leaf of Config."""
    for section in dataclasses.fields(Config):
        for f in dataclasses.fields(section.default):
            yield section.name, f.name, type(getattr(section.default, f.name))


def flag_value(value) -> str:
    """A config value as its flag spells it: tuples and lists comma-separated (the inverse of the parsing
    in :func:`from_flags`)."""
    return ",".join(map(str, value)) if isinstance(value, (tuple, list)) else str(value)


def as_flags(cfg: Config) -> list[str]:
    """The shortest command line for ``cfg``: ``--config=<the preset it differs least from>`` and a
    ``--<section>.<field>`` flag per field that differs (the inverse of :func:`from_flags`)."""

    def overrides(preset):
        return [
            f"--{section}.{name}={flag_value(getattr(getattr(cfg, section), name))}"
            for section, name, _ in fields()
            if getattr(getattr(cfg, section), name) != getattr(getattr(PRESETS[preset], section), name)
        ]

    preset = min(PRESETS, key=lambda name: len(overrides(name)))
    return [f"--config={preset}", *overrides(preset)]


def define_flags(flag_values=None) -> None:
    """Defines ``--config`` and one ``--<section>.<field>`` absl flag per config field (default: unset)."""
    from absl import flags

    fv = flags.FLAGS if flag_values is None else flag_values
    flags.DEFINE_string("config", "cpu", f"preset, one of {sorted(PRESETS)}", flag_values=fv)
    definers = {
        int: flags.DEFINE_integer,
        float: flags.DEFINE_float,
        str: flags.DEFINE_string,
        bool: flags.DEFINE_boolean,
    }
    for section, name, typ in fields():
        if typ is tuple:
            flags.DEFINE_list(f"{section}.{name}", None, "comma-separated integers", flag_values=fv)
        else:
            definers[typ](f"{section}.{name}", None, f"override {section}.{name}", flag_values=fv)


def from_flags(flag_values=None) -> Config:
    """The preset named by ``--config`` with every set ``--<section>.<field>`` applied, validated."""
    from absl import flags

    fv = flags.FLAGS if flag_values is None else flag_values
    cfg = get_config(fv["config"].value)
    overrides: dict[str, dict[str, Any]] = {}
    for section, name, typ in fields():
        value = fv[f"{section}.{name}"].value
        if value is None:
            continue
        if typ is tuple:
            try:
                value = tuple(int(v) for v in value)
            except ValueError:
                raise ValueError(f"--{section}.{name}={','.join(value)}: expected comma-separated integers")
        overrides.setdefault(section, {})[name] = value
    return validate(replace(cfg, **overrides))


def parse_flags(argv):
    """The launchers' absl ``flags_parser``: a bad flag exits with one line, not absl's usage text."""
    from absl import flags

    try:
        return flags.FLAGS(argv)
    except flags.Error as e:
        raise SystemExit(f"error: {e}")


# orbax reads a checkpoint's arrays as concurrent tasks on an event loop that it closes as soon as one read
# fails. The reads still in flight then report on their own, pages of text after the launcher's one error
# line: into the closed loop ('Event loop is closed', from tensorstore's threads), as coroutines collected
# mid-read, and as tasks and futures whose failure nobody retrieved (asyncio's log). Launchers drop those.
def _from_orbax(*texts: str) -> bool:
    return any(f"{os.sep}orbax{os.sep}" in text for text in texts)


def _without_abandoned_read_reports(hook):
    """``hook`` (a ``sys.unraisablehook``) less the reports of the reads orbax abandons."""

    def filtered(unraisable):
        closed_loop = (
            isinstance(unraisable.exc_value, RuntimeError) and str(unraisable.exc_value) == "Event loop is closed"
        )
        code = getattr(unraisable.object, "cr_code", None)
        trace = traceback.format_exception(unraisable.exc_type, unraisable.exc_value, unraisable.exc_traceback)
        if not (closed_loop or _from_orbax(code.co_filename if code else "", *trace)):
            hook(unraisable)

    return filtered


class _AbandonedReads(logging.Filter):
    """For asyncio's logger: drops its reports of the tasks and futures of the reads orbax abandons, logging
    them at DEBUG. Those reports carry orbax's frames, or (tensorstore's futures, which carry none) name
    the checkpoint whose restore failed: :func:`quieten_abandoned_reads` registers it."""

    def __init__(self):
        super().__init__()
        self.paths = set()

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        trace = logging.Formatter().formatException(record.exc_info) if record.exc_info else ""
        if not (_from_orbax(text, trace) or any(path in text for path in self.paths)):
            return True
        logging.getLogger(__name__).debug("%s", text)
        return False


_abandoned_reads = _AbandonedReads()


def quieten_abandoned_reads(path: str | None = None) -> None:
    """Drops asyncio's reports of the reads orbax abandons (the one filter; a logger holds a filter once),
    and those that name ``path``, a checkpoint whose restore failed. After such a failure, the reads'
    coroutines may also be collected unawaited, each with a warning at exit: those are dropped too."""
    if path is not None:
        _abandoned_reads.paths.add(path)
        warnings.filterwarnings("ignore", r"coroutine '.*' was never awaited", RuntimeWarning)
    logging.getLogger("asyncio").addFilter(_abandoned_reads)


def check_launch(argv, required: tuple = ("workdir",)) -> None:
    """A launcher's first checks: no positional arguments, each flag named in ``required`` given.
    Raises ValueError naming the flag. Also quietens the routine INFO lines jax and orbax log, and the
    reports of the reads orbax abandons when a checkpoint fails to restore (the failure is raised)."""
    from absl import flags
    from absl import logging as absl_logging

    if not flags.FLAGS["verbosity"].present:
        absl_logging.set_verbosity(absl_logging.WARNING)
    sys.unraisablehook = _without_abandoned_read_reports(sys.unraisablehook)
    quieten_abandoned_reads()
    if len(argv) > 1:
        raise ValueError(f"unexpected arguments {argv[1:]}; every setting is a --flag")
    for name in required:
        if not flags.FLAGS[name].value:
            raise ValueError(f"--{name} is required")
