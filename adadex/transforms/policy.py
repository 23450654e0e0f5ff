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
  carries one, see :meth:`adadex.transforms.modulation.ChannelTransform.state_shapes`). Like TorchRL's
  recurrent modules, the env must carry that state: ``env.append_transform(policy.primer())`` (a
  ``TensorDictPrimer`` that zeroes it at reset); without it the policy raises instead of silently
  forgetting its edits.

Before the modulator reads the observation, the policy shows it the carried edit (as the
transformed env does), so ``"observation"`` and the reference entries in the tensordict are the
edited ones, and writes the modulator's view; the tracker's own (further modulated) inputs live
only inside the policy call.

Example::

    policy = make_policy(tracker, modulator, channels="R+O+T")
    env = TransformedEnv(TrackingEnv(data, num_worlds=8), policy.primer())
    td = env.rollout(100, policy)
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import Composite, Unbounded
from torchrl.envs import TensorDictPrimer

from adadex.envs.observation import OBSERVATION
from adadex.modules.channels import MOD, ModulationConfig, ModulationLayout
from adadex.transforms.modulation import ChannelTransform, ModulatorView, modulation

SAMPLE = (MOD, "sample")


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
    """The graph built by :func:`make_policy` (a ``TensorDictSequential``)."""

    def __init__(self, *modules, layout: ModulationLayout, state_shapes: dict):
        super().__init__(*modules)
        self.layout, self.state_shapes = layout, dict(state_shapes)

    @property
    def persistent(self) -> bool:
        """Whether the policy carries channel state (R's persistent edit) from step to step."""
        return bool(self.state_shapes)

    def primer(self) -> TensorDictPrimer:
        """The state the env must carry for this policy (zeros at reset); empty without persistent R."""
        spec = {key: Unbounded(shape=shape) for key, shape in self.state_shapes.items()}
        return TensorDictPrimer(Composite(spec), default_value=0.0, expand_specs=True)


def make_policy(tracker, modulator=None, channels=None,
                config: ModulationConfig = ModulationConfig()) -> ModulatedPolicy:
    """Modulator → R, O → frozen tracker → T as one policy for a plain TrackingEnv.

    Args:
        tracker: the frozen generalist (:class:`adadex.modules.tracker.Tracker`); runs
            deterministically, without gradient, and is frozen by this call.
        modulator: an :class:`adadex.modules.modulator.Modulator`, or ``None`` for the tracker alone.
        channels: the channel set (default: the modulator's); must match the modulator's.
        config: λ's, bounds and persistence — the same values as the transformed env's.

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
    if stateful:
        modules.append(_ShowState(stateful))
    if modulator is not None:
        modules.append(getattr(modulator, "actor", modulator))
    modules.append(_TrackerStage(chain, layout, stateful))
    return ModulatedPolicy(*modules, layout=layout,
                           state_shapes={key: shape for t in stateful for key, shape in t.state_shapes().items()})
