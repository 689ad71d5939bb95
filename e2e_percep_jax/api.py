"""The trained perceiver, for other JAX code: load a run, then filter camera + lidar streams online.

    import jax
    import e2e_percep_jax as e2e
    perceiver, params = e2e.load("runs/demo")           # latest checkpoint of a training run
    state = perceiver.init(batch_size=4)                 # a model.FilterState for 4 streams
    step = jax.jit(perceiver.step, static_argnames="measure")
    state, out = step(params, state, camera, lidar, action, key=None)
    out.pose, state.pose.belief                          # a PerceiverOutputs; the pose belief's filter state
    boxes = perceiver.boxes(out)                         # per stream: (boxes [M, 5], scores [M])

``Perceiver.step`` is a pure function of its arguments (the perceiver itself holds only the frozen
config), so it goes inside the caller's ``jit``, ``vmap`` and ``lax.scan`` (called without ``jit``, it runs
op by op, many times slower). It runs the same posterior step as training's scanned rollout
(:func:`e2e_percep_jax.model.filter_sequence`), so streaming a sequence frame by frame reproduces the
training-time posterior. With the belief pose head (the presets) it also runs the pose belief's histogram
filter (:mod:`e2e_percep_jax.pose_belief`), so the pose it returns sharpens as a drive goes on. The online
evaluation perceives through this same ``step``.
"""

import dataclasses

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import checkpoint, detection, ego_motion, pose_belief, xla_cpu
from e2e_percep_jax import model as model_lib
from e2e_percep_jax.config import Config
from e2e_percep_jax.sim.motion import MotionModel


def _check(name, x, shape, dtype):
    """Trace-time check (shapes and dtypes are static, so this also works under jit)."""
    if tuple(x.shape) != tuple(shape) or x.dtype != dtype:
        raise ValueError(
            f"{name}: expected {jnp.dtype(dtype).name}{list(shape)}, got {jnp.dtype(x.dtype).name}{list(x.shape)}"
        )


@flax.struct.dataclass
class PerceiverOutputs:
    """What :meth:`Perceiver.step` returns for a frame of B streams (R = ``data.image_size``; a pytree).
    The baselines' perceivers (:mod:`e2e_percep_jax.baselines`) return it too, without what they lack.

    det_cls: float32 [B, R, R, 1], the vehicle probability of each bird's-eye pixel.
    det_reg: float32 [B, R, R, 6], the PIXOR regression (units in :mod:`e2e_percep_jax.sim.pixor`).
    pose: float32 [B, 5], the ego pose in the town frame (x m, y m, cos ψ, sin ψ, speed m/s). With the
        belief head: at the filtered belief's mode, or under ``--model.pose_filter=none`` the head's own
        mode this frame. NaN from a perceiver without a pose estimate.
    z: float32 [B, z1_dim + z2_dim], the latent (z1, z2) the maps are decoded from; None without a latent.
    camera, lidar, roadmap: float32 [B, R, R, 3] in [0, 1], the reconstructed images: those the variant
        reconstructs (``model.reconstructed_images``), the others None.
    pose_place: float32 [B, n, n], the pose belief's probability of each cell (row i along y, column j
        along x, ``pose_belief.Grid.cell_centres``); None without the belief head.
    """

    det_cls: jax.Array
    det_reg: jax.Array
    pose: jax.Array
    z: jax.Array | None = None
    camera: jax.Array | None = None
    lidar: jax.Array | None = None
    roadmap: jax.Array | None = None
    pose_place: jax.Array | None = None


def _leaf_names(state) -> list:
    """The names of a filter state's arrays, as its checks name them (``state.pose.belief``)."""
    return [f"state{jax.tree_util.keystr(path)}" for path, _ in jax.tree_util.tree_flatten_with_path(state)[0]]


def _absent(names: list, others: list) -> list:
    """The ``names`` not among ``others``, each as its shortest prefix that no name of ``others`` shares (a
    whole missing sub-state is named once: ``state.pose``), in order, without repeats."""
    out = []
    for name in names:
        if name in others:
            continue
        parts = name.split(".")
        prefix = next(
            p
            for p in (".".join(parts[:k]) for k in range(2, len(parts) + 1))
            if not any(o == p or o.startswith(p + ".") for o in others)
        )
        if prefix not in out:
            out.append(prefix)
    return out


@dataclasses.dataclass(frozen=True)
class Perceiver:
    """The perception model of ``cfg`` as pure functions of (params, filter state, inputs). ``motion_model``:
    the run's calibrated motion model (``motion_model.json``, :mod:`e2e_percep_jax.sim.motion`), through which
    the pose belief follows the commands; the default, the exact bicycle without lag or noise, is right
    only in a world whose plant has all its fields at zero."""

    cfg: Config
    motion_model: MotionModel = MotionModel()

    @property
    def belief(self) -> bool:
        return self.cfg.model.pose_head == "belief"

    @property
    def lidar_odometry(self) -> bool:
        """Whether the lidar's scans, given to :meth:`step`, correct the commands' motion (:func:`ego_motion.step`:
        the motion model has the scan matcher's fitted noise); ``measure=False`` then requires them."""
        return self.cfg.model.histogram_belief and ego_motion.uses_scans(self.motion_model)

    def init(self, batch_size: int) -> model_lib.FilterState:
        """The filter state (:class:`~e2e_percep_jax.model.FilterState`) before the first frame of
        ``batch_size`` streams; with the belief pose head its ``pose`` is the pose belief's
        (:class:`~e2e_percep_jax.pose_belief.PoseBeliefState`), else None.
        """
        if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
            raise ValueError(f"batch_size={batch_size!r}: must be a positive integer")
        state = model_lib.init_filter_state(batch_size, self.cfg)
        if self.belief:
            state = state.replace(pose=pose_belief.init_state(batch_size, pose_belief.grid_of(self.cfg.model)))
        return state

    def step(
        self,
        params,
        state: model_lib.FilterState,
        camera,
        lidar,
        action,
        key=None,
        start_pose=None,
        measure: bool = True,
        lidar_scan=None,
    ) -> tuple[model_lib.FilterState, PerceiverOutputs]:
        """Filters one frame of B streams and decodes it.

        state: :meth:`init`'s or the last step's; camera, lidar: uint8 [B, R, R, 3] (the frame contract's
        images); action: float32 [B, 2], the ego's commands from the previous frame to this one, as the car
        logs them (pedal in [-1, 1], steering command rad; ignored on a stream's first frame); key: a PRNG
        key to sample the latents, or None for the posterior means. Returns (state, :class:`PerceiverOutputs`).

        ``start_pose`` [B, 5] (belief head only): the known-start protocol. Streams starting a drive start
        their belief at this pose; it then follows the commands through the motion model and, with
        ``measure`` (the town the model was trained on), the place measurements as in the global protocol.
        ``measure=False`` (a town the model has not seen) is an odometry: the commands through the motion
        model, their heading, speed and distance corrected by the lidar's scans ``lidar_scan`` float32 [B, 360]
        (the frame contract's: ranges m a degree) when the model has the scan matcher's fitted noise
        (:attr:`lidar_odometry`, :mod:`e2e_percep_jax.ego_motion`). With ``measure``, ``lidar_scan`` is
        optional: given, the belief moves by that odometry between the place measurements, else by the
        commands alone. Nothing else reads ``lidar_scan``.
        """
        camera, lidar, action = jnp.asarray(camera), jnp.asarray(lidar), jnp.asarray(action)
        first = state.first if isinstance(state, model_lib.FilterState) else None
        b, r = (first.shape[0] if getattr(first, "ndim", 0) == 1 else camera.shape[0]), self.cfg.data.image_size
        _check("camera", camera, (b, r, r, 3), jnp.uint8)
        _check("lidar", lidar, (b, r, r, 3), jnp.uint8)
        _check("action", action, (b, 2), jnp.float32)
        if start_pose is not None:
            start_pose = jnp.asarray(start_pose)
            _check("start_pose", start_pose, (b, 5), jnp.float32)
        if lidar_scan is None and start_pose is not None and not measure and self.lidar_odometry:
            raise ValueError("lidar_scan: measure=False follows the lidar's scans; pass the frame's lidar_scan")
        if lidar_scan is not None and self.lidar_odometry:
            lidar_scan = jnp.asarray(lidar_scan)
            _check("lidar_scan", lidar_scan, (b, ego_motion.SCAN_AZIMUTHS), jnp.float32)
        self._check_state(state, b)
        latent_state, latent = model_lib.filter_step(params, state, camera, lidar, action, key, self.cfg)
        z = jnp.concatenate([latent["z1"], latent["z2"]], -1)
        decoded = model_lib.decode(params, latent, self.cfg)
        common = dict(det_cls=decoded["det_cls"], det_reg=decoded["det_reg"], z=z)
        common.update(
            {k: jnp.clip(decoded[k], 0.0, 1.0) for k in model_lib.reconstructed_images(self.cfg.model.variant)}
        )
        if not self.belief:
            return latent_state, PerceiverOutputs(pose=model_lib.pose_to_metres(decoded["pose_normalised"]), **common)
        head, grid = model_lib.pose_belief_head(params, latent, self.cfg), pose_belief.grid_of(self.cfg.model)
        if self.cfg.model.pose_filter == "histogram":
            pose_state, pose = pose_belief.filter_step(
                state.pose,
                head,
                action,
                state.first,
                grid,
                self.motion_model,
                start_pose=start_pose,
                measure=measure,
                scan=lidar_scan,
            )
        else:  # the frame's head alone: its own distribution is the belief
            pose_state, pose = pose_belief.head_state(head, grid, state.pose.odometry), pose_belief.decode(head, grid)
        pose_place = pose_belief.place_marginal(pose_state.belief)
        return latent_state.replace(pose=pose_state), PerceiverOutputs(pose=pose, pose_place=pose_place, **common)

    def pose_nll(self, state: model_lib.FilterState, pose):
        """-log density [B] of the true poses [B, 5] (metres) under the filtered pose belief (per m² and
        radian), NaN without the belief head."""
        if not self.belief:
            return jnp.full(pose.shape[:1], jnp.nan)
        return pose_belief.negative_log_likelihood(state.pose, pose, pose_belief.grid_of(self.cfg.model))

    def pose_coverage(self, state: model_lib.FilterState, pose):
        """How much of the true poses' [B, 5] cell lies in the pose belief's 95 % region: float [B, 2] in
        [0, 1], for the place and for the place with heading (:func:`pose_belief.region_share`); 0 without
        the belief head."""
        if not self.belief:
            return jnp.zeros(pose.shape[:1] + (2,))
        return pose_belief.region_share(state.pose, pose, pose_belief.grid_of(self.cfg.model))

    def _check_state(self, state, batch_size: int):
        """Trace-time check of a filter state against :meth:`init`'s for ``batch_size`` streams."""
        expected = jax.eval_shape(lambda: self.init(batch_size))
        if not isinstance(state, model_lib.FilterState):
            raise ValueError(f"state: expected the FilterState of Perceiver.init, got {type(state).__name__}")
        if jax.tree.structure(state) != jax.tree.structure(expected):
            want, got = _leaf_names(expected), _leaf_names(state)
            raise ValueError(
                f"state: expected the FilterState of Perceiver.init; missing {_absent(want, got)}, "
                f"unexpected {_absent(got, want)}"
            )
        for (path, want), got in zip(jax.tree_util.tree_flatten_with_path(expected)[0], jax.tree.leaves(state)):
            _check(f"state{jax.tree_util.keystr(path)}", jnp.asarray(got), want.shape, want.dtype)

    def boxes(
        self,
        outputs: PerceiverOutputs,
        score_threshold: float | None = None,
        iou_threshold: float = detection.NMS_IOU,
        merge_iou: float = detection.NMS_MERGE_IOU,
    ):
        """Host-side box decoding of :meth:`step`'s outputs: for each of the B streams, (boxes [M, 5]
        in the ego frame (x m, y m, yaw rad, length m, width m), scores [M]), highest score first,
        after greedy NMS on exact rotated IoU at ``iou_threshold``, each kept box merged with the boxes it
        suppresses above ``merge_iou`` (``metrics.merging_nms``; 1: none). ``score_threshold`` defaults to
        the config's."""
        threshold = self.cfg.eval.score_threshold if score_threshold is None else score_threshold
        cls_maps, reg_maps = np.asarray(outputs.det_cls), np.asarray(outputs.det_reg)
        return [
            detection.thresholded_boxes(cls_map, reg_map, threshold, iou_threshold, merge_iou)
            for cls_map, reg_map in zip(cls_maps, reg_maps)
        ]


def load(workdir: str, step: int | None = None):
    """(Perceiver, params) of the training run in ``workdir`` at checkpoint ``step`` (default: latest), with
    the run's calibrated motion model (``motion_model.json``) for the belief pose head.

    Called before this process's first computation, it also routes XLA:CPU's convolutions as the
    launchers do (:func:`e2e_percep_jax.xla_cpu.prefer_eigen_convolutions`, process-wide)."""
    xla_cpu.prefer_eigen_convolutions()
    cfg, params, _ = checkpoint.restore_params(workdir, step=step)
    return run_perceiver(cfg, workdir), params


def run_perceiver(cfg: Config, workdir: str) -> Perceiver:
    """The perceiver of run ``workdir`` under ``cfg``: with its motion model when it has the belief head
    (ValueError naming the file if the model is missing)."""
    return Perceiver(cfg, MotionModel.load(workdir) if cfg.model.pose_head == "belief" else MotionModel())
