"""``TrackingEnv``: B worlds tracking hand–object references, as one batched TorchRL environment.

Each world holds the robot, the table and the object of its current reference (scenes built with
``uniform_layout=True`` so worlds with different objects share one structure); all worlds advance
together through one :class:`~adadex.sim.batched.BatchedSim` rollout call per 12 Hz control step.
A reset draws a reference from a dataset split for each world being reset (partial resets reset
only the worlds flagged in ``"_reset"``), places the robot at the reference's joints and the object
at its pose at the episode's first frame.

Per step:

* action: 22-D change of the joint targets, ``q_target ← clip(q_target + action, joint limits)``,
  held by the position servos (PD) for the control step;
* observation: structured entries and the flat 273-D ``"observation"`` (see
  :mod:`adadex.envs.observation`), plus the current joint targets ``("proprio", "joint_target")``
  (not part of the 273-D vector), the object latent from ``latent_fn`` (default: the shipped point-cloud
  encoder's latent, :func:`adadex.envs.latent.encoder_latent`); the object's point cloud, for an
  encoder in the policy graph, is added by the transform :class:`adadex.transforms.object_points.ObjectPoints`;
* reward: :func:`adadex.envs.reward.tracking_reward`;
* ``"privileged"`` — ground truth for evaluation and logs, which a policy never reads (see
  :data:`adadex.envs.observation.PRIVILEGED`): ``("privileged", "errors")`` the per-frame metric
  errors T_o, R_o, T_h, R_h, E_finger (:func:`adadex.envs.frame_errors.frame_errors`), so evaluation
  never recomputes physics; ``("privileged", "reward_terms")`` the reward's terms;
  ``("privileged", "reference_index")`` / ``("privileged", "step")`` the dataset index of each world's
  reference and the frame's step within its episode (what an imitation term keys on);
  ``("privileged", "unstable")`` (below);
* ``terminated`` when the object or the palm drifts beyond the configured errors, or when the
  world's physics went unstable — NaN, a MuJoCo reset, or the object flung faster than
  ``max_object_speed`` (then ``("privileged", "unstable")`` is set, the world is put back to its
  reference start at once so no NaN leaves the env, and :attr:`TrackingEnv.unstable_count` grows);
  ``truncated`` at the end of the episode window.

On the default rollout backend the step runs on numpy arrays — the readouts MuJoCo fills, the
reference frames — through the same observation, error and reward functions the torch modules use
(:mod:`adadex.arrays`), and hands TorchRL tensors that share the arrays' memory: at B = 64 the env
runs at about 0.89 × the speed of its physics alone (``benchmarks/env_throughput.py``). On the warp
backend (``backend="warp"``) the env lives on the sim's device (a GPU when there is one): the same
functions run on torch tensors there, the reference frames are held there, the step's noise is drawn
there, and nothing but the step's unstable-world check is read back; resets (reference draws, scenes,
randomization, C MuJoCo's forward pass) stay host work written to the device. Command- and
sensor-stage effects of a patch run on the host, a round trip per step.

Physics randomization (:class:`~adadex.envs.randomization.Randomization`) draws an effect patch per
world at each reset — Table 3's scales, or ranges around a fitted patch:
``TrackingEnv(ds, randomize=Randomization.from_patch(ModelPatch.load("patch.json")))``. A patch and
randomization compose: each world's draw randomizes *around the patched robot*
(:meth:`Randomization.world_patch <adadex.envs.randomization.Randomization.world_patch>`) — a
drawn scale multiplies the patch's (``patch`` kp_scale 0.3 on arm_j1 under Table 3: a gain of
1500 · 0.3 · draw), a drawn offset adds to it, clipped to the effect's bounds; the ranges of
``Randomization.from_patch`` draw the fitted value itself and replace the patch's there.

Example
-------
``tiny_dataset`` is the folder of a built reference dataset (e.g. ``"data/small"``):

>>> from adadex.envs.tracking import TrackingEnv
>>> env = TrackingEnv(tiny_dataset, num_worlds=2, split=None)
>>> td = env.rollout(3)                      # random actions
>>> td["next", "privileged", "errors", "T_o"].shape
torch.Size([2, 3])
>>> env.close()
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from adadex.arrays import to_float
from adadex.data.reference import WINDOW_FRAMES, ReferenceDataset, check_frames, check_split
from adadex.data.reference import episode_references  # noqa: F401  (defined there; importable here as before)
from adadex.envs.frame_errors import ERROR_NAMES, frame_errors
from adadex.envs.latent import encoder_latent
from adadex.envs.observation import LATENT_DIM, OBS_DIM, PRIVILEGED, REF_OFFSETS, flat_observation
from adadex.envs.randomization import ModelRandomizer, Randomization
from adadex.envs.reward import TERM_NAMES, RewardConfig, tracking_reward
from adadex.errors import ArrayError, ConfigError, check_array, check_number, check_numbers
from adadex.geometry import Rotation, quat, rotation
from adadex.sim.batched import MAX_OBJECT_SPEED, BatchedSim, check_backend, flung
from adadex.sim.scene import MAX_TARGET_STEP
from adadex.sim.effects import ModelBase
from adadex.sim.patch import EffectInstance, ModelPatch, patched_scene
from adadex.sim.robot import NUM_JOINTS, TRACKED_SITES, joint_limits
from adadex.sim.scene import CONTROL_HZ, OBJECT_QPOS, resting_height

#: spawn key of the per-step noise stream (``TrackingEnv._set_seed``)
_STEP_STREAM = 1


@dataclass(frozen=True)
class TrackingConfig:
    """Episode, action and termination settings of a :class:`TrackingEnv` (lengths in m, angles in rad).

    One frozen value the env reads at construction, so an env's episodes are fully described by it;
    :meth:`adadex.train.config.TrainConfig.env_config` builds one with a run's reward settings.

    Attributes:
        window: frames tracked per episode (default 300, the paper's); the episode is truncated at its
            end. References with fewer frames from their window start are never drawn. At least 14
            (the farthest reference frame observed, t + 12, plus 2).
        max_action: largest change of a joint target per control step, rad (default 0.1): the action
            is clipped to ±``max_action``, and the randomization's action noise is in units of it.
        terminate_object_error: end the episode when the object's position error T_o exceeds this, m
            (default 0.25; 0: never).
        terminate_palm_error: end the episode when the palm's position error T_h exceeds this, m
            (default 0.25; 0: never).
        object_lift: how far above its reference pose the object starts each episode, m (default
            0.002: so that it does not start overlapping the table).
        max_object_speed: object speed above which a world's physics counts as unstable, m/s (default
            :data:`~adadex.sim.readout.MAX_OBJECT_SPEED`, 4: no tabletop motion is that fast, so the
            contact solver blew up); such a world is terminated and put back to its reference start.
        reward: the reward's weights and thresholds (default: :class:`RewardConfig`'s defaults).

    Example:
        >>> TrackingConfig(max_action=0.05).window
        300
    """

    window: int = WINDOW_FRAMES
    max_action: float = MAX_TARGET_STEP
    terminate_object_error: float = 0.25
    terminate_palm_error: float = 0.25
    object_lift: float = 0.002
    max_object_speed: float = MAX_OBJECT_SPEED
    reward: RewardConfig = field(default_factory=RewardConfig)

    def __post_init__(self):
        if self.window < max(REF_OFFSETS) + 2:
            raise ConfigError(f"window must be at least {max(REF_OFFSETS) + 2} frames, got {self.window}")
        check_numbers("TrackingConfig", self,
                      ("max_action", "terminate_object_error", "terminate_palm_error", "object_lift", "max_object_speed"))


def env_device(backend: str, device=None) -> torch.device:
    """Where a :class:`TrackingEnv` on ``backend`` steps and hands out its tensors: the CPU for the rollout
    backend (MuJoCo on the CPU cores); for ``"warp"``, ``device`` (a Warp or torch device name) or Warp's
    default device — a GPU when there is one, so nothing leaves it on the step's hot path."""
    if check_backend(backend) == "rollout":
        if device is not None and torch.device(device).type != "cpu":
            raise ConfigError(f"TrackingEnv(device={str(device)!r}): the rollout backend runs MuJoCo on the CPU "
                              f"and hands out CPU tensors; use backend='warp' for a GPU, or keep the env on the "
                              f"CPU and put the policy on the GPU through the collector (policy_device)")
        return torch.device("cpu")
    from adadex.sim.warp_backend import torch_device

    return torch_device(device)


def _as_patch(patch, effects) -> ModelPatch:
    out = ModelPatch() if patch is None else (patch if isinstance(patch, ModelPatch) else ModelPatch.load(patch))
    for e in effects or ():
        if isinstance(e, EffectInstance):
            out = out + ModelPatch((e,))
        else:
            out = out.with_effect(*e)
    return out


def scene_pack(dataset, references, *, randomize: Randomization | None = None, patch=None,
               effects=None) -> dict:
    """Every scene a :class:`TrackingEnv` over ``references`` may compile — each object at each
    randomization size, with the env's patch (and its structure alone, when randomizing) — as the
    ``scenes`` argument of the env. Compiled once here, pickled cheaply into workers (0.7 ms to load
    a scene against ~50 ms to compile one), so a worker's env starts without compiling."""
    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    full = _as_patch(patch, effects)
    if randomize is not None and randomize.patch is not None:
        full = randomize.patch.updated(full)
    patches = [full] + ([full.stage("structure")] if randomize is not None else [])
    scales = randomize.scale_levels() if randomize is not None else np.array([1.0])
    objects = sorted({ds.entries[int(i)]["object"] for i in references})
    pack = {}
    for name in objects:
        for scale in scales:
            for p in patches:
                key = (name, float(scale), p.content_key())
                if key not in pack:
                    pack[key] = patched_scene(name, p, uniform_layout=True, object_scale=float(scale))
    return pack


class TrackingEnv(EnvBase):
    """B worlds tracking hand–object references as one batched TorchRL env (the tracker's and, under
    :func:`~adadex.transforms.modulation.modulation`, the modulator's training env).

    All worlds step together through one physics call per 12 Hz control step, so PPO collects B
    episodes at the cost of one batched rollout; each world resets on its own, drawing a new
    reference (and, with ``randomize``, new physics). Actions, observations, rewards, the
    ``"privileged"`` ground truth and the termination rules are described in the module docstring.

    Args:
        dataset: a reference dataset (folder or :class:`ReferenceDataset`).
        num_worlds: B, worlds stepped together (default 8).
        split: ``(split name, part)`` to draw references from (default the unseen-trajectory training
            part), or ``None`` for all references; ignored when ``references`` is given.
        config: episode, action, termination and reward settings (default: :class:`TrackingConfig`'s
            defaults).
        latent_fn: object name → (64,) latent (default: the shipped point-cloud encoder's latent,
            :func:`~adadex.envs.latent.encoder_latent`).
        randomize: per-world domain randomization (:class:`Randomization`), or ``None`` (default: the
            nominal physics, no noise); e.g. ``Randomization()`` for Table 3, or
            ``Randomization.from_patch(ModelPatch.load("patch.json"))`` around a fitted patch.
        patch: a model patch (file or :class:`ModelPatch`) applied to every world (its entries
            replace ``randomize.patch``'s on the same effect and joint); under randomization each
            world's draw composes with it (see the module docstring: scales multiply, offsets add;
            ``from_patch``'s ranges draw the value itself). ``None`` (default): no patch.
        effects: effects applied to every world, as ``EffectInstance`` or ``(effect, joints, values)``,
            added to ``patch`` (default none).
        nthread: threads of the physics rollout pool (default 2; 0 steps physics on the env's own
            thread).
        seed: seeds the reference draws, the randomization's draws and the noise (default 0); two
            envs with the same seed meet the same noise in every episode they share.
        draw: ``"random"`` (default: each reset draws a reference at random) or ``"cycle"`` (world
            ``w`` takes the split's references ``w, w + B, w + 2B, …`` in turn: every reference once,
            for evaluation).
        references: dataset indices to draw from instead of a split (e.g. one evaluation chunk);
            each needs a ``config.window``-frame episode window.
        device: where the env steps and hands out its tensors (:func:`env_device`): ``None`` (default)
            is the CPU for the rollout backend and Warp's default device (a GPU when there is one) for
            the warp backend; the rollout backend refuses any other than the CPU (a policy on a GPU gets
            its inputs through the collector's ``policy_device``).
        scenes: compiled scenes to use instead of compiling them (:func:`scene_pack`; a collector's
            workers get them from the main process, so they start without compiling). ``None``
            (default): compile them here.
        backend: the physics of :class:`~adadex.sim.batched.BatchedSim`: ``"rollout"`` (default,
            MuJoCo on the CPU cores) or ``"warp"`` (MuJoCo Warp on its default device, a GPU when there
            is one; ``pip install "adadex[warp]"``), with the env on that device (``device``).
        group_size: worlds per group of common random numbers (default 1: every world draws alone).
            The ``group_size`` consecutive worlds of a group start together on one reference, one
            randomization draw and one object displacement, and meet the same action and sensor noise
            every step, so they differ only in what their policy does (what PPO's group advantage
            compares, :func:`adadex.train.ppo.group_advantage`). A world whose episode ends early
            restarts alone on its own draw and is truncated when its group's episode ends, so that
            the group starts together again. Must divide ``num_worlds``; needs ``draw="random"``.

    Example:
        >>> env = TrackingEnv(tiny_dataset, num_worlds=2, split=None, draw="cycle")
        >>> env.reset()["observation"].shape
        torch.Size([2, 273])
        >>> env.close()
    """

    batch_locked = True

    def __init__(self, dataset, *, num_worlds: int = 8, split: tuple[str, str] | None = ("unseen_trajectory", "train"),
                 config: TrackingConfig = TrackingConfig(),
                 latent_fn: Callable[[str], np.ndarray] = encoder_latent,
                 randomize: Randomization | None = None, patch=None, effects=None,
                 nthread: int = 2, seed: int = 0, draw: str = "random", references=None, device=None,
                 scenes: dict | None = None, backend: str = "rollout", group_size: int = 1):
        num_worlds = int(check_number("TrackingEnv num_worlds", num_worlds, low=1, integer=True))
        group_size = int(check_number("TrackingEnv group_size", group_size, low=1, integer=True))
        if num_worlds % group_size:
            raise ConfigError(f"TrackingEnv group_size={group_size} must divide num_worlds={num_worlds}")
        if group_size > 1 and draw != "random":
            raise ConfigError(f"TrackingEnv group_size={group_size} needs draw='random' (got {draw!r}): a group "
                              f"shares one random draw")
        device = env_device(check_backend(backend), device)
        super().__init__(device=device, batch_size=torch.Size([num_worlds]))
        #: the step's array namespace: numpy on the host (rollout backend), torch on the sim's device (warp)
        self._xp = np if backend == "rollout" else torch
        self.dataset = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
        self.config = config
        self.latent_fn = latent_fn
        if draw not in ("random", "cycle"):
            raise ConfigError(f"draw must be 'random' or 'cycle', got {draw!r}")
        self.draw = draw
        #: worlds per group of common random numbers (1: every world draws alone)
        self.group_size = group_size
        self._resets = np.zeros(num_worlds, dtype=np.int64)
        self.randomize = randomize
        self.patch = _as_patch(patch, effects)
        if randomize is not None and randomize.patch is not None:
            self.patch = randomize.patch.updated(self.patch)
        self._has_sensor_effects = bool(len(self.patch.active().stage("sensor")))
        self._ranges = randomize.effect_ranges() if randomize is not None else ()
        #: The effect patch each world currently runs (the env's patch and its randomization draw).
        self.world_patches: list[ModelPatch] = [self.patch] * num_worlds
        self._shipped = dict(scenes or {})
        self._scenes: dict[tuple[str, float], mujoco.MjModel] = {}
        self._nominal: dict[tuple[str, float], tuple[mujoco.MjModel, ModelBase]] = {}
        self._scales = randomize.scale_levels() if randomize is not None else np.array([1.0])
        self._scale = np.ones(num_worlds)
        self._action_offset = self._array(np.zeros((num_worlds, NUM_JOINTS)))
        self._has_command_effects = any(e.spec.stage == "command" for e in self.patch.active().effects)
        self._servo_cmd = np.zeros((num_worlds, NUM_JOINTS))   # what the servos last received
        self.references = self._usable(check_split(split), references)
        check_frames(self.dataset, self.references)      # a bad frame is refused here, not turned into NaN
        # The step runs on numpy arrays (rollout backend) or on torch tensors on the sim's device (warp
        # backend: nothing leaves the device on the step's hot path); the per-frame functions it calls take
        # either (adadex.arrays). It hands TorchRL tensors sharing the arrays' memory. Observations, errors
        # and rewards are float32 end to end (no per-step casts); on the host the joint targets are float64.
        # Resets are host work (draws, scenes, C MuJoCo's forward pass), written into the step's arrays.
        frames = self.dataset.frames
        self._ref_q = frames["hand_joint_pos"].to(torch.float32).numpy().copy()       # host: resets read them
        self._ref_link = frames["hand_link_pose"].to(torch.float32).numpy().copy()
        self._ref_obj = frames["object_pose"].to(torch.float32).numpy().copy()
        self._step_ref_q, self._step_ref_link, self._step_ref_obj = (
            self._array(a) for a in (self._ref_q, self._ref_link, self._ref_obj))    # the step's copies
        B = num_worlds
        self._base = self._array(np.zeros(B, dtype=np.int64))       # frame index of each world's episode start
        self._t = self._array(np.zeros(B, dtype=np.int64))
        self._group_t = self._array(np.zeros(B, dtype=np.int64))    # steps since the group last started together
        self._ref_index = self._array(np.zeros(B, dtype=np.int64))
        self._latent = self._array(np.zeros((B, LATENT_DIM), dtype=np.float32))
        # object pose seen at each episode's first frame
        self._object_start = self._array(np.zeros((B, 7), dtype=np.float32))
        lim = joint_limits()
        self._limits = lim                                          # host: resets clip to them
        self._lo, self._hi = self._array(lim[:, 0].copy()), self._array(lim[:, 1].copy())
        self._offsets = self._array(np.asarray(REF_OFFSETS)[None])
        self._q_target = self._array(np.zeros((B, NUM_JOINTS)))
        self.unstable_count = 0
        self._set_seed(seed)
        first = self.dataset.entries[self.references[0]]["object"]
        objects = sorted({self.dataset.entries[i]["object"] for i in self.references})
        # Compile every scene once; the data shared by the worlds is sized for the largest.
        scenes = [self._scene(n, 1.0) for n in objects]
        biggest = max(scenes, key=lambda m: (m.nC, m.nbvh, m.nbvhdynamic))
        self.sim = BatchedSim([biggest] + [self._scene(first, 1.0)] * (B - 1), nthread=nthread, backend=backend,
                              **({} if backend == "rollout" else {"device": str(self.device)}))
        self.sim.set_models([0], [self._scene(first, 1.0)])
        self._randomizer = ModelRandomizer(biggest) if randomize is not None else None
        self._make_specs()

    # -- setup ------------------------------------------------------------------------------------
    def _scene(self, object_name: str, scale: float) -> mujoco.MjModel:
        """The uniform-layout scene of one object at one size with the env's patch (shared, read-only);
        kept for the env's life, so a reset never compiles twice whatever the shared cache drops."""
        key = (object_name, scale)
        if key not in self._scenes:
            self._scenes[key] = self._compiled(object_name, scale, self.patch)
        return self._scenes[key]

    def _compiled(self, object_name: str, scale: float, patch: ModelPatch) -> mujoco.MjModel:
        """A scene from the ``scenes`` shipped to this env (see :func:`scene_pack`), else compiled."""
        shipped = self._shipped.get((object_name, float(scale), patch.content_key()))
        if shipped is not None:
            return shipped
        return patched_scene(object_name, patch, uniform_layout=True, object_scale=scale)

    def _randomized_scene(self, object_name: str, scale: float, rng: np.random.Generator
                          ) -> tuple[mujoco.MjModel, ModelPatch]:
        """A world's own model: the scene compiled with the patch's structure only (nominal parameters),
        copied, its object randomized, then the env's patch with this world's draw composed on it
        (:meth:`Randomization.world_patch`) applied by the effects."""
        key = (object_name, scale)
        if key not in self._nominal:
            m = self._compiled(object_name, scale, self.patch.stage("structure"))
            self._nominal[key] = (m, ModelBase.of(m))
        nominal, base = self._nominal[key]
        model = self._randomizer.apply(nominal, self.randomize, rng)
        patch = self.randomize.world_patch(self.patch, rng, self._ranges)
        patch.apply_model(model, base)
        return model, patch

    def _usable(self, split, references=None) -> list[int]:
        if references is not None:
            bad = [i for i in references if not 0 <= int(i) < len(self.dataset)]
            if bad or not len(references):
                raise ConfigError(f"{self.dataset.path}: references must be a non-empty list of indices in "
                                 f"[0, {len(self.dataset)}), got {list(references)[:10]}")
            usable = set(episode_references(self.dataset, None, self.config.window))
            short = [int(i) for i in references if int(i) not in usable]
            if short:
                raise ConfigError(f"{self.dataset.path}: references {short} have no {self.config.window}-frame window")
            return [int(i) for i in references]
        ok = episode_references(self.dataset, split, self.config.window)
        if not ok:
            raise ConfigError(f"{self.dataset.path}: no reference in split {split} has a "
                             f"{self.config.window}-frame episode window")
        return ok

    def _make_specs(self) -> None:
        B = self.batch_size

        def u(*shape):
            return Unbounded(shape=(*B, *shape), dtype=torch.float32, device=self.device)

        K, L = len(REF_OFFSETS), len(TRACKED_SITES)
        self.observation_spec = Composite(
            proprio=Composite(joint_pos=u(NUM_JOINTS), joint_target=u(NUM_JOINTS), link_pose=u(L, 7), shape=B),
            object=Composite(pose=u(7), latent=u(LATENT_DIM), start_pose=u(7), reference_start=u(7), shape=B),
            reference=Composite(hand_joint_pos=u(K, NUM_JOINTS), hand_link_pose=u(K, L, 7), object_pose=u(K, 7),
                                shape=B),
            observation=u(OBS_DIM),
            # True in the worlds a reset (re)started: what TorchRL's InitTracker would add, published by
            # the env itself so a user's Collector(env, policy) has nothing to append or warn about
            is_init=Categorical(2, shape=(*B, 1), dtype=torch.bool, device=self.device),
            privileged=Composite(
                errors=Composite({k: u() for k in ERROR_NAMES}, shape=B),
                unstable=Categorical(2, shape=(*B, 1), dtype=torch.bool, device=self.device),
                reward_terms=Composite({k: u() for k in TERM_NAMES}, shape=B),
                reference_index=Unbounded(shape=B, dtype=torch.int64, device=self.device),
                step=Unbounded(shape=B, dtype=torch.int64, device=self.device), shape=B),
            shape=B, device=self.device)
        m = self.config.max_action
        self.action_spec = Bounded(low=-m, high=m, shape=(*B, NUM_JOINTS), dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded(shape=(*B, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            done=Categorical(2, shape=(*B, 1), dtype=torch.bool, device=self.device),
            terminated=Categorical(2, shape=(*B, 1), dtype=torch.bool, device=self.device),
            truncated=Categorical(2, shape=(*B, 1), dtype=torch.bool, device=self.device),
            shape=B, device=self.device)

    def _set_seed(self, seed: int | None):
        """Two streams: ``_rng`` draws what a (re)start sets (references, Table 3's per-episode draws,
        the start's sensor noise), ``_step_rng`` the per-step action and sensor noise, always for every
        world at once. So a world's episode never shifts another's noise: a world that ends early and
        restarts draws only from the first stream, and two policies evaluated with the same seed meet
        the same noise in every episode they share (paired comparisons stay paired)."""
        self._rng = np.random.default_rng(seed)
        if self._xp is np:
            self._step_rng = np.random.default_rng(None if seed is None else [int(seed), _STEP_STREAM])
        else:       # drawn on the device: the same seed gives the same noise there (not numpy's values)
            self._step_rng = torch.Generator(device=self.device)
            s = np.random.SeedSequence(None if seed is None else [int(seed), _STEP_STREAM]).generate_state(2)
            self._step_rng.manual_seed(int(s[0]) << 32 | int(s[1]))
        return seed

    # -- references -------------------------------------------------------------------------------
    def _frames_at(self) -> np.ndarray:
        """(B, 5) frame indices of the reference at t + REF_OFFSETS, held at the window's last frame."""
        return self._base[:, None] + (self._t[:, None] + self._offsets).clip(max=self.config.window - 1)

    def _draw_units(self, worlds: np.ndarray) -> np.ndarray:
        """For each of ``worlds`` (being reset), the index of the draw it takes: the worlds of a whole
        group (``group_size`` consecutive worlds, all of them in ``worlds``) share one; any other world
        draws alone (a world restarting by itself after its episode ended early)."""
        G = self.group_size
        if G == 1:
            return np.arange(len(worlds))
        blocks = np.asarray(worlds) // G
        counts = dict(zip(*np.unique(blocks, return_counts=True)))
        ids: dict = {}
        return np.asarray([ids.setdefault(("group", b) if counts[b] == G else ("world", w), len(ids))
                           for w, b in zip(worlds, blocks)], dtype=np.int64)

    def _start_worlds(self, worlds: np.ndarray) -> None:
        """Draw references for ``worlds`` and put them at their episode start (a whole group of
        ``group_size`` worlds: one draw for all of them)."""
        unit = self._draw_units(worlds)
        first = np.unique(unit, return_index=True)[1]              # a world of each draw, in draw order
        if self.draw == "random":
            picks = self._rng.choice(self.references, size=len(first))[unit]
        else:
            B = self.batch_size[0]
            picks = [self.references[(w + B * self._resets[w]) % len(self.references)] for w in worlds]
        self._resets[worlds] += 1
        models, bases, latents, offsets = [], [], [], []
        cfg = self.randomize
        for j in first:
            w, r = worlds[j], picks[j]
            e = self.dataset.entries[r]
            bases.append(e["offset"] + e["window_start"])
            latents.append(np.asarray(self.latent_fn(e["object"]), dtype=np.float32))
            self._scale[w] = self._rng.choice(self._scales)
            if cfg is not None:
                model, self.world_patches[w] = self._randomized_scene(e["object"], float(self._scale[w]), self._rng)
                offsets.append(self._rng.normal(0, cfg.action_noise_correlated, NUM_JOINTS))
            else:
                model = self._scene(e["object"], float(self._scale[w]))
            models.append(model)
        for j, u in enumerate(unit):                # the group's other worlds take its draw
            self._scale[worlds[j]] = self._scale[worlds[first[u]]]
            self.world_patches[worlds[j]] = self.world_patches[worlds[first[u]]]
        self._assign(self._ref_index, worlds, np.asarray(picks, dtype=np.int64))
        self._assign(self._base, worlds, np.asarray(bases, dtype=np.int64)[unit])
        self._assign(self._latent, worlds, np.stack(latents)[unit])
        if offsets:
            self._assign(self._action_offset, worlds, np.stack(offsets)[unit])
        self.sim.set_models(worlds, [models[u] for u in unit])
        self._assign(self._t, worlds, 0)
        whole = worlds[np.bincount(unit)[unit] > 1] if self.group_size > 1 else worlds
        self._assign(self._group_t, whole, 0)
        self._put_at_start(worlds, np.asarray(bases, dtype=np.int64)[unit], perturb=cfg is not None, unit=unit)

    def _put_at_start(self, worlds: np.ndarray, b: np.ndarray, perturb: bool = False,
                      unit: np.ndarray | None = None) -> None:
        """Put ``worlds`` at the reference frames ``b`` (their episodes' first frames); ``perturb``: with
        the object displaced, one draw per ``unit`` (default: one per world)."""
        q = np.clip(self._ref_q[b].astype(np.float64), self._limits[:, 0], self._limits[:, 1])
        obj = self._ref_obj[b].astype(np.float64)
        obj[:, 2] += self.config.object_lift
        for j, w in enumerate(worlds):   # a resized object still rests on the table
            scale = self._scale[w]
            obj[j, 2] += (scale - 1.0) / scale * resting_height(self.sim.models[w])
        if perturb and self.randomize is not None:
            cfg = self.randomize
            unit = np.arange(len(worlds)) if unit is None else unit
            n = int(unit.max()) + 1
            obj[:, :2] += self._rng.normal(0, cfg.object_xy_std, (n, 2))[unit]
            yaw = Rotation.from_euler("z", self._rng.normal(0, cfg.object_yaw_std, (n, 1))[unit])
            obj[:, 3:] = quat(yaw * rotation(obj[:, 3:]))
        qpos = np.zeros((len(worlds), self.sim.models[0].nq))
        qpos[:, :NUM_JOINTS] = q
        qpos[:, OBJECT_QPOS] = obj
        # one call (on the warp backend, one device write); the servos have been holding q: a delayed or
        # lagged servo starts from it
        self.sim.reset(qpos=qpos, worlds=worlds, ctrl=q)
        self._assign(self._q_target, worlds, q)
        self._servo_cmd[worlds] = q

    # -- TorchRL ----------------------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        worlds = np.arange(self.batch_size[0]) if mask is None else \
            np.flatnonzero(mask.reshape(self.batch_size).cpu().numpy())
        if len(worlds):
            self._start_worlds(worlds)
        readout = self._readout()
        self._assign(self._object_start, worlds, readout.object_pose[self._index(worlds)])
        out, _ = self._observe(readout, self._rng)
        B, dev = self.batch_size, self.device
        out[PRIVILEGED].update({"unstable": torch.zeros(*B, 1, dtype=torch.bool, device=dev),
                                "reward_terms": self._td({k: torch.zeros(*B, device=dev) for k in TERM_NAMES})})
        out[PRIVILEGED] = self._td(out[PRIVILEGED])
        out["is_init"] = (torch.ones(*B, 1, dtype=torch.bool, device=dev) if mask is None
                          else mask.reshape(*B, 1).to(device=dev, dtype=torch.bool).clone())
        return self._td(out)

    def step(self, tensordict: TensorDictBase) -> TensorDictBase:
        """TorchRL's ``step`` with the action's shape checked first: TorchRL checks the tensordict's batch
        size before :meth:`_step` runs, so an action of another batch shape would be refused by its batch
        check, which names neither ``action`` nor the shape it must have."""
        self._action(tensordict)
        return super().step(tensordict)

    def _action(self, tensordict: TensorDictBase):
        """The tensordict's ``"action"``, of the action spec's shape; an :class:`ArrayError` naming it if not."""
        want = tuple(self.action_spec.shape)
        action = tensordict.get("action", None) if isinstance(tensordict, TensorDictBase) else None
        if action is None:
            raise ArrayError(f"action: missing from the tensordict given to step; expected a tensor of shape {want}")
        got = tuple(getattr(action, "shape", ()))
        if got != want:
            raise ArrayError(f"action: expected shape {want}, got {got} (one row of {want[-1]} joint "
                             f"targets per world, {want[0]} worlds)")
        return action

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        cfg = self.config
        action = self._action(tensordict).detach()
        action = check_array("action", action.cpu().numpy() if self._xp is np else action.to(self.device, torch.float32),
                             tuple(self.action_spec.shape))
        if self.randomize is not None:     # in units of the action bound, before it (as Isaac Gym's VecTask)
            noise = self._action_offset + self._noise(self._step_rng, self.randomize.action_noise_uncorrelated,
                                                      tuple(action.shape))
            action = action + cfg.max_action * noise
        action = action.clip(-cfg.max_action, cfg.max_action)
        self._q_target = (self._q_target + action).clip(self._lo, self._hi)
        readout = self._sim_step(self._servo_command())
        self._t += 1
        self._group_t += 1
        # MuJoCo flags diverging worlds; an object flung faster than any tabletop motion is one too.
        unstable = readout.unstable | flung(readout.object_vel, cfg.max_object_speed)
        if unstable.any():                      # on the device, a read back
            worlds = np.flatnonzero(self._host(unstable))
            self.unstable_count += len(worlds)
            self._assign(self._t, worlds, 0)
            self._put_at_start(worlds, self._host(self._base)[worlds])   # no NaN leaves the env; it ends below
            readout = self._readout()
            self._assign(self._object_start, worlds, readout.object_pose[self._index(worlds)])
        out, frame = self._observe(readout, self._step_rng)
        err = frame["errors"]
        reward, terms = tracking_reward(cfg.reward, **frame)
        terminated = unstable
        if cfg.terminate_object_error > 0:
            terminated = terminated | (err["T_o"] > cfg.terminate_object_error)
        if cfg.terminate_palm_error > 0:
            terminated = terminated | (err["T_h"] > cfg.terminate_palm_error)
        truncated = self._t >= cfg.window - 1
        if self.group_size > 1:          # a world restarted alone ends with its group, which then starts together
            truncated = truncated | (self._group_t >= cfg.window - 1)
        terms["termination"] = cfg.reward.w_termination * to_float(terminated, reward)
        reward = reward - terms["termination"]
        t = self._tensor
        out.update(reward=t(reward[:, None]), terminated=t(terminated[:, None]), truncated=t(truncated[:, None]),
                   done=t((terminated | truncated)[:, None]),
                   is_init=torch.zeros(*self.batch_size, 1, dtype=torch.bool, device=self.device))
        out[PRIVILEGED].update({"unstable": t(unstable[:, None]),
                                "reward_terms": self._td({k: self._float32(v) for k, v in terms.items()})})
        out[PRIVILEGED] = self._td(out[PRIVILEGED])
        return self._td(out)

    def _step_proc_data(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        """TorchRL's pass over a step's output reshapes the reward and fills in missing done keys;
        ``_step`` writes them all in their spec shapes, so the pass is skipped unless
        ``run_type_checks`` asks for TorchRL's checks."""
        if self.run_type_checks:
            return super()._step_proc_data(next_tensordict)
        return next_tensordict

    def _td(self, entries: dict) -> TensorDict:
        """A TensorDict of the env's batch size from entries whose shapes are right by construction
        (skips TensorDict's per-entry validation: this runs every step)."""
        return TensorDict._new_unsafe(entries, batch_size=self.batch_size, device=self.device)

    def _servo_command(self):
        """Targets → what the servos receive: command-stage effects (backlash …) run online, as the
        workbench's sequence transform applied to (last servo command, new target) — on the host (for
        the warp backend, a round trip per step with such effects)."""
        cmd = self._q_target
        if self._has_command_effects:
            seq = np.stack([self._servo_cmd, self._host(cmd).astype(np.float64)], axis=1)
            self._servo_cmd = self.patch.transform_command(seq, 1.0 / CONTROL_HZ)[:, 1].copy()
            cmd = self._array(self._servo_cmd)
        return cmd

    # -- the step's arrays: numpy on the host (rollout backend), torch on the sim's device (warp) ----
    def _array(self, host: np.ndarray):
        """``host`` as an array of the step (itself, or a tensor on the env's device; float64 → float32 there)."""
        if self._xp is np:
            return host
        out = torch.as_tensor(host, device=self.device)
        return out.to(torch.float32) if out.dtype == torch.float64 else out

    @staticmethod
    def _host(x) -> np.ndarray:
        """A step array on the host (numpy)."""
        return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x

    def _index(self, worlds: np.ndarray):
        """World indices for a step array."""
        return worlds if self._xp is np else torch.as_tensor(worlds, device=self.device)

    def _assign(self, arr, worlds: np.ndarray, values) -> None:
        """``arr[worlds] = values`` for a step array, from host values (or a step array)."""
        if self._xp is np:
            arr[worlds] = values
        else:
            arr[self._index(worlds)] = torch.as_tensor(values, device=self.device).to(arr.dtype)

    def _tensor(self, x) -> torch.Tensor:
        """A step array as a tensor (sharing its memory)."""
        return x if isinstance(x, torch.Tensor) else torch.from_numpy(x)

    def _float32(self, x) -> torch.Tensor:
        if isinstance(x, torch.Tensor):
            return x.to(torch.float32)
        return torch.from_numpy(np.asarray(x, dtype=np.float32))

    @staticmethod
    def _copy(x):
        return x.clone() if isinstance(x, torch.Tensor) else x.copy()

    def _noise(self, rng, sigma: float, shape: tuple, f32: bool = False):
        """Gaussian noise for a step array: from a numpy generator (float32 if ``f32``; moved to the
        device for the warp backend), or drawn on the device from a torch generator (float32). The
        worlds of a group (``group_size``) meet the same noise."""
        G = self.group_size
        drawn = (shape[0] // G, *shape[1:])
        if isinstance(rng, torch.Generator):
            n = sigma * torch.randn(drawn, generator=rng, device=self.device)
            return n.repeat_interleave(G, dim=0) if G > 1 else n
        n = rng.normal(0, sigma, drawn)
        if G > 1:
            n = np.repeat(n, G, axis=0)
        return self._array(n.astype(np.float32) if f32 else n)

    def _readout(self):
        """The sim's readout of every world: numpy on the host, or the warp backend's device readout."""
        return self.sim.readout() if self._xp is np else self.sim.device_readout()

    def _sim_step(self, cmd):
        return self.sim.step(cmd) if self._xp is np else self.sim.step_device(cmd)

    def _observe(self, readout, rng: np.random.Generator) -> tuple[dict, dict]:
        """Entries of the structured and flat observation plus the frame errors, for the current frame
        of every world, and the true (not sensed) state with the current reference frame and errors
        as numpy arrays, the reward's arguments. Computed on numpy arrays, handed out as torch tensors
        sharing their memory (every array here is new this step, so no output aliases the env's state)."""
        f32 = np.float32
        # copies: the host readout is reused (the device readout's tensors are new, float32 already)
        joint_pos, link_pose, object_pose = (x if isinstance(x, torch.Tensor) else x.astype(f32)
                                             for x in (readout.joint_pos, readout.link_pose, readout.object_pose))
        idx = self._frames_at()
        ref_q, ref_link, ref_obj = self._step_ref_q[idx], self._step_ref_link[idx], self._step_ref_obj[idx]
        # What the policy sees: encoders (sensor-stage effects, noise) and noisy link positions.
        seen_q = joint_pos
        if self._has_sensor_effects:      # on the host
            seen_q = self._array(self.patch.transform_measurement(self._host(seen_q).astype(np.float64)[:, None])
                                 [:, 0].astype(f32))
        seen_link = link_pose
        if self.randomize is not None and self.randomize.proprio_noise > 0:
            sigma = self.randomize.proprio_noise
            seen_q = seen_q + self._noise(rng, sigma, tuple(seen_q.shape), f32=True)
            seen_link = self._copy(seen_link)
            seen_link[..., :3] += self._noise(rng, sigma, tuple(seen_link[..., :3].shape), f32=True)
        latent = self._copy(self._latent)
        flat = flat_observation(seen_q, seen_link, object_pose, latent, ref_q, ref_obj)
        errors = frame_errors(object_pose, ref_obj[:, 0], link_pose[:, 0], ref_link[:, 0, 0], joint_pos, ref_q[:, 0])
        frame = {"joint_pos": joint_pos, "link_pose": link_pose, "object_pose": object_pose, "ref_joint_pos": ref_q[:, 0],
                 "ref_link_pose": ref_link[:, 0], "ref_object_pose": ref_obj[:, 0], "errors": errors}
        t, td, c = self._tensor, self._td, self._copy
        out = {
            "proprio": td({"joint_pos": t(seen_q), "joint_target": self._float32(c(self._q_target)),
                           "link_pose": t(seen_link)}),
            "object": td({"pose": t(object_pose), "latent": t(latent), "start_pose": t(c(self._object_start)),
                          "reference_start": t(self._step_ref_obj[self._base])}),
            "reference": td({"hand_joint_pos": t(ref_q), "hand_link_pose": t(ref_link), "object_pose": t(ref_obj)}),
            "observation": t(flat),
            PRIVILEGED: {"errors": td({k: t(v) for k, v in errors.items()}),
                         "reference_index": t(c(self._ref_index)), "step": t(c(self._t))},
        }
        return out, frame

    # -- info -------------------------------------------------------------------------------------
    @property
    def current_references(self) -> list[str]:
        """Name of each world's current reference."""
        return [self.dataset.entries[int(i)]["name"] for i in self._host(self._ref_index)]

    def close(self, **kwargs):
        self.sim.close()
        super().close(**kwargs)
