"""``ObjectPoints``: each world's object point cloud, ``("object", "points")``, as a TorchRL transform.

The tracking env gives its policy the object latent read from a table (``latent_fn``,
:func:`adadex.envs.latent.encoder_latent`) and never the object's shape itself, so a policy graph
cannot hold the point-cloud encoder (:class:`adadex.modules.encoder.PointCloudEncoder`). This
transform adds the encoder's input: for every world, the surface cloud of the object of the
reference it tracks, (…, N, 3) float32 in the object frame in metres — the very cloud the shipped
latent table was computed from (:func:`adadex.modules.encoder.surface_points` of the object,
``points`` = 512, seed :data:`~adadex.modules.encoder.LATENT_SEED`), so the encoder in the graph
gives the table's latent.

Why a transform and not an env option: the points are a pure function of what the env already
publishes, the dataset index of each world's reference, ``("privileged", "reference_index")``; a
transform keeps the env free of the model layer's sampling settings (lower layers never import
upper ones), costs nothing to users who do not want the points (they add B × N × 3 floats to every
frame of a rollout: 6 KB per world at N = 512), composes like any TorchRL transform (``env.append_transform``, inside or outside a
``SerialEnv``/``ParallelEnv``) and declares its entry in the observation spec, so
``check_env_specs`` and collectors see it. It writes the points at reset and again at every step
from the step's own reference index (the env publishes it in both), so it carries no episode state
(only a cache of the clouds sampled so far, one per object): partial resets, auto-resets and worlds put back at their start after unstable physics all show the right
object. :meth:`adadex.transforms.policy.ModulatedPolicy.primer` includes it when the policy holds
the encoder.

The cloud is the object at its nominal size: under randomization the env may resize an object
(Table 3's scales), but its latent from the table ignores that too; both see the object's shape.

Example
-------
>>> from torchrl.envs import TransformedEnv
>>> from adadex.envs.tracking import TrackingEnv
>>> env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None), ObjectPoints())
>>> td = env.rollout(3)
>>> td["object", "points"].shape, env.observation_spec["object", "points"].shape
(torch.Size([2, 3, 512, 3]), torch.Size([2, 512, 3]))
>>> env.close()
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import Transform

from adadex.data.reference import ReferenceDataset
from adadex.envs.observation import REFERENCE_INDEX
from adadex.errors import ConfigError, UnknownKeyError, check_number
from adadex.modules.encoder import LATENT_SEED, OBJECT_POINTS, EncoderConfig, surface_points

#: Points per cloud by default: the encoder's (and its latent table's) ``EncoderConfig.points``.
DEFAULT_POINTS = EncoderConfig().points


class ObjectPoints(Transform):
    """Writes each world's object point cloud, ``("object", "points")`` (…, N, 3), from the reference
    index the env publishes; see the module docstring.

    Args:
        dataset: the env's reference dataset (folder or :class:`~adadex.data.reference.ReferenceDataset`);
            by default the one of the env this transform is appended to (a :class:`TrackingEnv`);
            give it when the base env is a ``SerialEnv``/``ParallelEnv`` or the transform runs alone.
        points: N, points per cloud (default 512, what the shipped encoder's latent table used).
        seed: the surface-sampling seed (default :data:`~adadex.modules.encoder.LATENT_SEED`, the table's).
        index_key: the key of each world's dataset index (default ``("privileged", "reference_index")``).
        out_key: the key written (default ``("object", "points")``, what
            :class:`~adadex.modules.encoder.PointCloudEncoder` reads).

    Example:
        >>> from torchrl.envs import TransformedEnv
        >>> from adadex.envs.tracking import TrackingEnv
        >>> env = TrackingEnv(tiny_dataset, num_worlds=2, split=None)
        >>> env = TransformedEnv(env, ObjectPoints(points=128))
        >>> env.reset()["object", "points"].shape
        torch.Size([2, 128, 3])
        >>> env.close()
    """

    def __init__(self, dataset=None, *, points: int = DEFAULT_POINTS, seed: int = LATENT_SEED,
                 index_key=REFERENCE_INDEX, out_key=OBJECT_POINTS):
        super().__init__(in_keys=[index_key], out_keys=[out_key])
        self.points = int(check_number("ObjectPoints points", points, low=1, integer=True))
        self.seed = int(check_number("ObjectPoints seed", seed, integer=True))
        self.index_key, self.out_key = index_key, out_key
        if dataset is not None and not isinstance(dataset, ReferenceDataset):
            dataset = ReferenceDataset(dataset)
        self._dataset = dataset
        self._row: torch.Tensor | None = None            # dataset index → row of _clouds (−1: not loaded yet)
        self._clouds = torch.zeros(0, self.points, 3)    # one cloud per object met so far
        self._objects: dict[str, int] = {}

    @property
    def dataset(self) -> ReferenceDataset:
        """The reference dataset whose indices the env publishes (given, or the parent env's)."""
        if self._dataset is None:
            parent = self.parent
            base = getattr(parent, "base_env", parent)
            found = getattr(base, "dataset", None)
            if not isinstance(found, ReferenceDataset):
                where = "not appended to an env" if parent is None else f"its base env {type(base).__name__} has none"
                raise ConfigError(f"ObjectPoints needs the env's reference dataset ({where}): pass it, "
                                  "ObjectPoints(dataset)")
            self._dataset = found
        return self._dataset

    def clouds(self, index: torch.Tensor) -> torch.Tensor:
        """(…, N, 3) float32: the cloud of the object of each dataset index in ``index`` (…,)."""
        ds = self.dataset
        if self._row is None:
            self._row = torch.full((len(ds),), -1, dtype=torch.int64)
        index = index.to("cpu", torch.int64)
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= len(ds)):
            bad = int(index[(index < 0) | (index >= len(ds))][0])
            raise ConfigError(f"ObjectPoints: reference index {bad} is not in {ds.path} ({len(ds)} references); "
                              "was it given another dataset than the env's?")
        rows = self._row[index]
        if bool((rows < 0).any()):                      # objects met for the first time: sample them once
            new = []
            for i in index[rows < 0].unique().tolist():
                name = ds.entries[i]["object"]
                if name not in self._objects:
                    self._objects[name] = len(self._objects)
                    new.append(torch.from_numpy(surface_points(name, self.points, self.seed).copy()))
                self._row[i] = self._objects[name]
            if new:
                self._clouds = torch.cat([self._clouds, torch.stack(new)])
            rows = self._row[index]
        return self._clouds[rows]

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        index = next_tensordict.get(self.index_key, None)
        if index is None:
            raise UnknownKeyError(f"ObjectPoints reads each world's reference index {self.index_key}, which is not "
                                  "in the tensordict (a TrackingEnv publishes it; keep the 'privileged' entries)")
        next_tensordict.set(self.out_key, self.clouds(index).to(next_tensordict.device))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The transform applied offline (to a stored tensordict, in a replay buffer …): the same as in the env."""
        return self._call(tensordict)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec[self.out_key] = Unbounded(shape=(*observation_spec.shape, self.points, 3),
                                                   dtype=torch.float32, device=observation_spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(points={self.points}, seed={self.seed}, out_key={self.out_key})"
