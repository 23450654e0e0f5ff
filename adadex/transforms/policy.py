"""The modulated policy as one graph for a plain TrackingEnv: modulator → R, O → tracker → T.

:func:`make_policy` builds the same computation as ``TransformedEnv(env, modulation(channels,
tracker))`` driven by the modulator, but as a policy, so a plain :class:`TrackingEnv` (and its
collectors, evaluation loops, gymnasium users) runs the modulated tracker. The channel transforms
of :mod:`adadex.transforms.modulation` do the work in both places — nothing is written twice —
and for the same seed both give identical actions and trajectories (tested).

The policy writes:

* ``"action"`` — the 22-D joint-target change for the env;
* ``("modulation", "sample")`` — the modulator's flat action (its ``"action_log_prob"`` and
  ``("modulator", "loc"/"scale")`` stay as the modulator wrote them);
* with the persistent R channel, ``("next", "modulation", "hand_edit"/"object_edit")`` — the
  reference edit carried to the next step, and for a modulator that reads its view
  (:mod:`adadex.modules.modulator_view`) the view's state, ``("next", "modulation",
  "last_action"/"steps"/"history")`` (in general: the state of every transform of the chain that
  carries one, see :meth:`adadex.transforms.modulation.ChannelTransform.state_shapes`), and a modulator's
  recurrent core its hidden state, ``("next", "modulator", "core_state")``. Like TorchRL's
  recurrent modules, the env must carry that state: ``env.append_transform(policy.primer())`` (a
  ``TensorDictPrimer`` that zeroes it at reset); without it the policy raises instead of silently
  forgetting its edits.

With ``encoder=`` (a :class:`~adadex.modules.encoder.PointCloudEncoder`) the point-cloud encoder is
the graph's first node: the object latent ``("object", "latent")`` comes from the object's point
cloud ``("object", "points")`` instead of the env's table (``latent_fn``), and the tracker's and the
modulator's 273-D ``"observation"`` is rebuilt with it (:func:`adadex.envs.observation.flat_from_tensordict`).
The encoder runs once per episode, in the worlds whose ``"is_init"`` is set (the env's first frame
after a reset), without gradient; its latent is carried to the later steps as state,
``("encoder", "latent")``, by the same primer. The env must emit the points:
:class:`~adadex.transforms.object_points.ObjectPoints`, which ``policy.primer()`` then includes.

Before the modulator reads the observation, the policy shows it the carried edit (as the
transformed env does), so ``"observation"`` and the reference entries in the tensordict are the
edited ones, and writes the modulator's view; the tracker's own (further modulated) inputs live
only inside the policy call.

Example::

    policy = make_policy(tracker, modulator, channels="R+O+T")
    env = TransformedEnv(TrackingEnv(data, num_worlds=8), policy.primer())
    td = env.rollout(100, policy)

    # the encoder in the graph: the same, with the latent computed from the object's points
    policy = make_policy(tracker, modulator, channels="R+O+T", encoder=PointCloudEncoder(load_encoder(path)[0]))
    env = TransformedEnv(TrackingEnv(data, num_worlds=8), policy.primer())   # ObjectPoints + state
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import Composite, Unbounded
from torchrl.envs import Compose, TensorDictPrimer, Transform

from adadex.envs.observation import JOINT_POS, LATENT_DIM, LINK_POSE, OBJECT_LATENT, OBJECT_POSE, OBSERVATION, \
    REF_JOINT_POS, REF_OBJECT_POSE, flat_from_tensordict
from adadex.errors import ConfigError, ConfigTypeError, UnknownKeyError
from adadex.modules.channels import MOD, ModulationConfig, ModulationLayout
from adadex.modules.encoder import PointCloudAutoencoder, PointCloudEncoder
from adadex.modules.nets import recurrent_state_shapes
from adadex.transforms.modulation import ChannelTransform, ModulatorView, modulation
from adadex.transforms.object_points import DEFAULT_POINTS, ObjectPoints

SAMPLE = (MOD, "sample")
#: The encoder's latent carried from an episode's first step to its later ones (the primer's state).
ENCODED_LATENT = ("encoder", "latent")
#: The entries :func:`flat_from_tensordict` reads besides the latent.
_STRUCTURED = (JOINT_POS, LINK_POSE, OBJECT_POSE, REF_JOINT_POS, REF_OBJECT_POSE)


class _EncodeObject(TensorDictModuleBase):
    """The point-cloud encoder as the graph's first node: ``("object", "points")`` → ``("object",
    "latent")`` in the worlds starting an episode (``"is_init"``), the carried latent elsewhere; the
    273-D observation rebuilt with it, and the latent carried to the next step."""

    def __init__(self, encoder):
        super().__init__()
        self.encoder = encoder
        self.points_key, self.latent_key = encoder.in_keys[0], encoder.out_keys[0]
        self.in_keys = [self.points_key, "is_init", ENCODED_LATENT, *_STRUCTURED]
        self.out_keys = [OBJECT_LATENT, OBSERVATION, ("next", *ENCODED_LATENT)]

    def _need(self, td: TensorDictBase, key, how: str) -> torch.Tensor:
        value = td.get(key, None)
        if value is None:
            raise UnknownKeyError(f"the policy's point-cloud encoder needs {key} in the tensordict: {how}")
        return value

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        points = self._need(td, self.points_key, "the env emits no object point clouds; add them with "
                            "env.append_transform(policy.primer()) (it includes ObjectPoints) or "
                            "env.append_transform(ObjectPoints()) (adadex.transforms.object_points)")
        carried = self._need(td, ENCODED_LATENT, "the latent it carries between steps; add it to the env "
                             "with env.append_transform(policy.primer())")
        first = self._need(td, "is_init", "True in the worlds starting an episode, where it encodes; a "
                           "TrackingEnv publishes it, another env needs torchrl.envs.InitTracker()")
        first = first.reshape(carried.shape[:-1])
        latent = carried
        if bool(first.any()):
            with torch.no_grad():
                cloud = points[first]
                z = self.encoder(TensorDict({self.points_key: cloud}, batch_size=cloud.shape[:1],
                                            device=td.device)).get(self.latent_key)
            latent = carried.clone()
            latent[first] = z.to(latent.dtype)
        td.set(OBJECT_LATENT, latent)
        td.set(OBSERVATION, flat_from_tensordict(td))
        td.set(("next", *ENCODED_LATENT), latent)
        return td


def _as_encoder(encoder):
    """A :class:`PointCloudEncoder` (or any TensorDictModule with one input and one output key) for
    :func:`make_policy`; a bare :class:`PointCloudAutoencoder` is wrapped."""
    if isinstance(encoder, PointCloudAutoencoder):
        encoder = PointCloudEncoder(encoder)
    if not isinstance(encoder, TensorDictModuleBase) or len(encoder.in_keys) != 1 or len(encoder.out_keys) != 1:
        raise ConfigTypeError(f"make_policy(encoder=…) takes a PointCloudEncoder (or a PointCloudAutoencoder), "
                              f"got {type(encoder).__name__}")
    auto = getattr(encoder, "autoencoder", None)
    if auto is not None and auto.config.latent_dim != LATENT_DIM:
        raise ConfigError(f"make_policy(encoder=…): the encoder's latent has {auto.config.latent_dim} entries, "
                          f"the tracker's observation holds {LATENT_DIM}")
    return encoder


class _ShowState(TensorDictModuleBase):
    """Applies the carried state to the env's raw observation (the transforms' forward path: R's
    persistent reference edit, then the modulator's view), so the modulator reads what the
    transformed env shows."""

    def __init__(self, channels: list):
        super().__init__()
        self.channels = nn.ModuleList(channels)
        self.state_keys = [key for t in channels for key in t.state_shapes()]
        self.in_keys = [*self.state_keys, OBSERVATION]
        self.out_keys = [OBSERVATION] + [out for t in channels for out in t.out_keys]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        for key in self.state_keys:
            if td.get(key, None) is None:
                raise KeyError(f"the modulated policy needs its state {key} in the tensordict: add it to the env "
                               "with env.append_transform(policy.primer())")
        for t in self.channels:
            td = t._call(td)
        return td


class _TrackerStage(TensorDictModuleBase):
    """The modulator's action → channel inverses → frozen tracker → env action, on a shallow copy
    so that nothing the modulator read is overwritten; writes back the action and the next state."""

    def __init__(self, chain, layout: ModulationLayout, stateful: list):
        super().__init__()
        self.chain, self.layout, self.stateful = chain, layout, stateful
        self.in_keys = [OBSERVATION, "action"]
        self.out_keys = ["action", SAMPLE] + [("next", *key) for t in stateful for key in t.state_shapes()]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        inner = td.clone(False)
        if not self.layout.dim:   # no channel: no modulator wrote an action
            inner.set("action", torch.zeros(*td.batch_size, 0, device=td.device))
        inner = self.chain._inv_call(inner)
        if self.layout.dim:
            td.set(SAMPLE, td.get("action"))
        td.set("action", inner.get("action"))
        for t in self.stateful:
            for key, value in t.next_state(inner).items():
                td.set(("next", *key), value)
        return td


class ModulatedPolicy(TensorDictSequential):
    """The graph built by :func:`make_policy` (a ``TensorDictSequential``).

    Args:
        *modules: the graph's modules, in order.
        layout: the modulator's action layout.
        state_shapes: ``{key: shape}`` of the state the policy carries from step to step (empty:
            none; :meth:`primer` makes the env carry it).
        points: the :class:`~adadex.transforms.object_points.ObjectPoints` settings when the
            point-cloud encoder is in the graph, else None.
    """

    def __init__(self, *modules, layout: ModulationLayout, state_shapes: dict, points: dict | None = None):
        super().__init__(*modules)
        self.layout, self.state_shapes = layout, dict(state_shapes)
        self._points = points          # ObjectPoints' settings when the encoder is in the graph

    @property
    def persistent(self) -> bool:
        """Whether the policy carries state from step to step (R's persistent edit, the modulator's
        view, the encoder's latent), i.e. needs its :meth:`primer`."""
        return bool(self.state_shapes)

    @property
    def encoder(self):
        """The point-cloud encoder in the graph, or ``None`` (the latent is the env's)."""
        first = self.module[0]
        return first.encoder if isinstance(first, _EncodeObject) else None

    def primer(self) -> Transform:
        """What the env must carry for this policy: a ``TensorDictPrimer`` of its state (zeros at reset;
        empty without persistent R, view, encoder or recurrent core) and, with the encoder in the graph,
        first an :class:`~adadex.transforms.object_points.ObjectPoints` (the encoder's input, the cloud its
        latent table used) — then a ``Compose`` of the two. A new transform at each call (one per env)."""
        primer = state_primer(self.state_shapes)
        if self._points is None:
            return primer
        return Compose(ObjectPoints(**self._points), primer)


def state_primer(state_shapes: dict) -> TensorDictPrimer:
    """A ``TensorDictPrimer`` of ``{key: shape}`` (per world; the env's batch dimensions are added):
    zeros at reset, carried from step to step by the env — the state a policy graph or a recurrent
    module (:func:`adadex.modules.nets.recurrent_state_shapes`) needs in the env.

    Args:
        state_shapes: ``{key: shape}`` per world.
    """
    spec = {key: Unbounded(shape=shape) for key, shape in state_shapes.items()}
    return TensorDictPrimer(Composite(spec), default_value=0.0, expand_specs=True)


def make_policy(tracker, modulator=None, channels=None,
                config: ModulationConfig = ModulationConfig(), encoder=None) -> ModulatedPolicy:
    """[Encoder →] modulator → R, O → frozen tracker → T as one policy for a plain TrackingEnv.

    Args:
        tracker: the frozen generalist (:class:`adadex.modules.tracker.Tracker`); runs
            deterministically, without gradient, and is frozen by this call.
        modulator: an :class:`adadex.modules.modulator.Modulator`, or ``None`` for the tracker alone.
        channels: the channel set (default: the modulator's); must match the modulator's.
        config: λ's, bounds and persistence — the same values as the transformed env's.
        encoder: a :class:`~adadex.modules.encoder.PointCloudEncoder` (or a bare
            :class:`~adadex.modules.encoder.PointCloudAutoencoder`, wrapped) to compute the object
            latent in the graph from ``("object", "points")``, once per episode (see the module
            docstring); ``None`` (default): the env's latent, as before. It runs without gradient
            (it is trained by its own Chamfer loss, :mod:`adadex.train.encoder`) and is not frozen.

    Example: the README's policy graph in miniature — the same graph as a policy for a plain env
    gives the same trajectory as the modulator on ``TransformedEnv(env, modulation(…))``.

    >>> import torch
    >>> from torchrl.envs import TransformedEnv
    >>> from adadex.envs.tracking import TrackingEnv
    >>> from adadex.modules.modulator import Modulator
    >>> from adadex.modules.tracker import Tracker
    >>> tracker = Tracker(hidden=(32, 32)).freeze()
    >>> modulator = Modulator("R+O+T", hidden=(32, 32))
    >>> policy = make_policy(tracker, modulator, channels="R+O+T")
    >>> plain = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None), policy.primer())
    >>> a = plain.rollout(3, policy)
    >>> a["action"].shape, a["modulation", "sample"].shape      # the env's action, the modulator's
    (torch.Size([2, 3, 22]), torch.Size([2, 3, 198]))
    >>> env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None),
    ...                      modulation("R+O+T", tracker, view=modulator.view))
    >>> b = env.rollout(3, modulator.actor)
    >>> torch.equal(a["next", "proprio", "joint_pos"], b["next", "proprio", "joint_pos"])
    True
    >>> plain.close(); env.close()

    With the shipped encoder in the graph, on an env whose own latent is zero, the tracker sees the
    same latent as from the env's table:

    >>> from adadex.envs.latent import SHIPPED_ENCODER, encoder_latent
    >>> from adadex.modules.encoder import PointCloudEncoder, load_encoder
    >>> policy = make_policy(tracker, encoder=PointCloudEncoder(load_encoder(SHIPPED_ENCODER)[0]))
    >>> zero = lambda name: torch.zeros(64).numpy()
    >>> env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, latent_fn=zero),
    ...                      policy.primer())
    >>> td = policy(env.reset())
    >>> objects = [env.base_env.dataset.entries[int(i)]["object"] for i in td["privileged", "reference_index"]]
    >>> table = torch.stack([torch.tensor(encoder_latent(name)) for name in objects])
    >>> torch.allclose(td["object", "latent"], table, atol=1e-5)
    True
    >>> env.close()
    """
    layout = ModulationLayout(channels if channels is not None else
                              (modulator.layout.channels if modulator is not None else "none"))
    if modulator is None and layout.dim:
        raise ValueError(f"channels {layout.name} need a modulator; pass modulator=… or channels='none'")
    if modulator is not None and modulator.layout.channels != layout.channels:
        raise ValueError(f"the modulator was built for channels {modulator.layout.name}, not {layout.name}")
    view = getattr(modulator, "view", None)
    chain = modulation(layout.channels, tracker, config, view=view)
    # Transforms carrying state, in the chain's (forward-path) order: R's edit, then the view.
    stateful = [t for t in chain if isinstance(t, (ChannelTransform, ModulatorView)) and t.state_shapes()]
    modules = []
    state_shapes = {key: shape for t in stateful for key, shape in t.state_shapes().items()}
    points = None
    if encoder is not None:
        encoder = _as_encoder(encoder)
        auto = getattr(encoder, "autoencoder", None)
        points = {"points": auto.config.points if auto is not None else DEFAULT_POINTS,
                  "out_key": encoder.in_keys[0]}
        modules.append(_EncodeObject(encoder))
        state_shapes = {ENCODED_LATENT: (LATENT_DIM,), **state_shapes}
    if stateful:
        modules.append(_ShowState(stateful))
    if modulator is not None:
        modules.append(getattr(modulator, "actor", modulator))
        state_shapes.update(recurrent_state_shapes(modules[-1]))     # a recurrent core's hidden state
    modules.append(_TrackerStage(chain, layout, stateful))
    return ModulatedPolicy(*modules, layout=layout, state_shapes=state_shapes, points=points)
