"""Env factories for collectors: picklable, one seed per worker, cheap to start in a new process.

A TorchRL collector calls ``create_env_fn()`` in each worker (a spawned process, or a Ray actor);
:class:`TrackingEnvFactory` carries everything the env needs — the dataset folder, the references,
the configs and the worker's own seed — so workers draw different references and randomizations.

>>> f = TrackingEnvFactory("data/small", references=(0, 1, 2), num_worlds=8, seed=3)
>>> [w.seed for w in f.for_workers(2)]
[1003, 2003]
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from torchrl.envs import RewardSum, TransformedEnv

from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingConfig, TrackingEnv, env_device, scene_pack
from adadex.modules.channels import ModulationConfig
from adadex.modules.modulator_view import ViewLayout
from adadex.modules.tracker import Tracker
from adadex.transforms.modulation import modulation
from adadex.transforms.policy import state_primer


@dataclass(frozen=True)
class TrackingEnvFactory:
    """Builds ``TrackingEnv(dataset, references=…, num_worlds=…, seed=…)``; see the module docstring.

    Calling it returns the env, with each episode's return summed into ``("next", "episode_reward")``.

    Attributes:
        dataset: the reference dataset folder.
        references: the dataset indices its worlds draw from.
        num_worlds: worlds stepped together (default 64).
        seed: the env seed (:meth:`for_workers` gives each worker its own).
        randomize: the per-world randomization (Table 3), or None: the nominal env.
        config: the episode settings (:class:`~adadex.envs.tracking.TrackingConfig`).
        nthread: the physics rollout's threads (default 2).
        patch: an effect patch (:class:`~adadex.sim.patch.ModelPatch`) on the robot, or None.
        scenes: compiled scenes carried to the workers (:meth:`with_scenes`); None: compiled by the env.
        transform: a picklable callable returning a transform appended after the env (e.g.
            :class:`ModulatedEnv`), or None.
        transforms: picklable zero-argument callables, each returning a transform appended last, after
            ``transform`` and ``RewardSum`` (a user's own: ``PPOTrainer(env_transforms=…)``).
        backend: the physics backend (:data:`adadex.sim.batched.BACKENDS`; config ``sim.backend``;
            default ``"rollout"``).
        group_size: worlds that share their episodes' draws and noise (default 1; config
            ``collector.group_size``; :class:`~adadex.envs.tracking.TrackingEnv`).
    """

    dataset: str
    references: tuple[int, ...]
    num_worlds: int = 64
    seed: int = 0
    randomize: Randomization | None = None
    config: TrackingConfig = field(default_factory=TrackingConfig)
    nthread: int = 2
    patch: object = None
    scenes: dict | None = field(default=None, repr=False, compare=False)
    #: a picklable callable returning a transform appended after the env (e.g. :class:`ModulatedEnv`)
    transform: object = None
    #: picklable zero-argument callables, each returning a transform appended last, after ``transform`` and
    #: ``RewardSum`` (a user's own: ``PPOTrainer(env_transforms=…)``)
    transforms: tuple = ()
    #: the physics backend (:data:`adadex.sim.batched.BACKENDS`; config ``sim.backend``)
    backend: str = "rollout"
    #: worlds that share their episodes' draws and noise (``collector.group_size``)
    group_size: int = 1

    @property
    def device(self):
        """Where the env steps and hands out its tensors (:func:`~adadex.envs.tracking.env_device`): the CPU,
        or Warp's default device for ``backend="warp"``."""
        return env_device(self.backend)

    def __call__(self) -> TransformedEnv:
        """The env, with each episode's return summed into ``("next", "episode_reward")`` for the logs,
        then the ``transforms``' transforms in order."""
        env = TrackingEnv(self.dataset, num_worlds=self.num_worlds, split=None, references=list(self.references),
                          config=self.config, randomize=self.randomize, patch=self.patch, nthread=self.nthread,
                          seed=self.seed, scenes=self.scenes, backend=self.backend,
                          group_size=self.group_size)
        env = TransformedEnv(env)
        if self.transform is not None:
            env.append_transform(self.transform())
        env.append_transform(RewardSum())
        for make in self.transforms:
            env.append_transform(make())
        return env

    def with_scenes(self) -> TrackingEnvFactory:
        """This factory carrying its compiled scenes (:func:`~adadex.envs.tracking.scene_pack`): compiled
        once here, they travel to each worker with the factory, so workers start without compiling."""
        if self.scenes is not None:
            return self
        return replace(self, scenes=scene_pack(self.dataset, self.references, randomize=self.randomize,
                                               patch=self.patch))

    def for_workers(self, n: int) -> list[TrackingEnvFactory]:
        """One factory per worker, worker ``i`` seeded ``1000·(i + 1) + seed`` (distinct draws)."""
        return [replace(self, seed=1000 * (i + 1) + self.seed) for i in range(n)]


@dataclass(frozen=True)
class ModulatedEnv:
    """Picklable ``modulation(channels, tracker, config, view)`` factory: each worker loads the frozen
    tracker from its checkpoint and builds the modulation transform (paper Sec. 3.2); ``history``
    (not None) adds the modulator's view with that many previous frames.

    Attributes:
        tracker: the frozen tracker's checkpoint path.
        channels: the active channels (default ``"R+O+T"``).
        config: the channels' settings (:class:`~adadex.modules.channels.ModulationConfig`).
        history: previous frames in the modulator's view, or None (default): no view.
        decide_every: the modulator's decision interval (the view's; its action held in between).
    """

    tracker: str
    channels: str = "R+O+T"
    config: ModulationConfig = field(default_factory=ModulationConfig)
    history: int | None = None
    decide_every: int = 1

    def __call__(self):
        view = None if self.history is None else ViewLayout(self.channels, self.history, self.decide_every)
        return modulation(self.channels, Tracker.load(self.tracker).freeze(), self.config, view=view)


@dataclass(frozen=True)
class StatePrimer:
    """Picklable :func:`~adadex.transforms.policy.state_primer` factory: the env carries this state from
    step to step, zeros at reset (a recurrent policy's hidden state, in each collector worker).

    Attributes:
        shapes: ``((key, shape), …)`` per world, e.g. ``((("modulator", "core_state"), (1, 128)),)``.
    """

    shapes: tuple

    def __call__(self):
        return state_primer(dict(self.shapes))
