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
  reference edit carried to the next step. Like TorchRL's recurrent modules, the env must carry
  that state: ``env.append_transform(policy.primer())`` (a ``TensorDictPrimer`` that zeroes it at
  reset); without it the policy raises instead of silently forgetting its edits.

Before the modulator reads the observation, the policy shows it the carried edit (as the
transformed env does), so ``"observation"`` and the reference entries in the tensordict are the
edited ones; the tracker's own (further modulated) inputs live only inside the policy call.

Example::

    policy = make_policy(tracker, modulator, channels="R+O+T")
    env = TransformedEnv(TrackingEnv(data, num_worlds=8), policy.primer())
    td = env.rollout(100, policy)
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.data import Composite, Unbounded
from torchrl.envs import TensorDictPrimer

from adadex.envs.observation import OBSERVATION
from adadex.modules.channels import EDIT_SHAPES, HAND_EDIT, MOD, OBJECT_EDIT, ModulationConfig, ModulationLayout
from adadex.transforms.modulation import ReferenceModulation, modulation, shift_edit

SAMPLE = (MOD, "sample")


class _ShowEdit(TensorDictModuleBase):
    """Applies the carried reference edit to the env's raw observation (the R transform's forward path)."""

    def __init__(self, reference: ReferenceModulation):
        super().__init__()
        self.reference = reference
        self.in_keys = [HAND_EDIT, OBJECT_EDIT, OBSERVATION]
        self.out_keys = [OBSERVATION]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        if td.get(HAND_EDIT, None) is None:
            raise KeyError("the persistent reference channel needs its edit state in the tensordict: "
                           "add it to the env with env.append_transform(policy.primer())")
        return self.reference._call(td)


class _TrackerStage(TensorDictModuleBase):
    """The modulator's action → channel inverses → frozen tracker → env action, on a shallow copy
    so that nothing the modulator read is overwritten; writes back the action and the next edit."""

    def __init__(self, chain, layout: ModulationLayout, persistent: bool):
        super().__init__()
        self.chain, self.layout, self.persistent = chain, layout, persistent
        self.in_keys = [OBSERVATION, "action"]
        self.out_keys = ["action", SAMPLE] + ([("next", *HAND_EDIT), ("next", *OBJECT_EDIT)] if persistent else [])

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        inner = td.clone(False)
        if not self.layout.dim:   # no channel: no modulator wrote an action
            inner.set("action", torch.zeros(*td.batch_size, 0, device=td.device))
        inner = self.chain._inv_call(inner)
        if self.layout.dim:
            td.set(SAMPLE, td.get("action"))
        td.set("action", inner.get("action"))
        if self.persistent:
            td.set(("next", *HAND_EDIT), shift_edit(inner.get(HAND_EDIT)))
            td.set(("next", *OBJECT_EDIT), shift_edit(inner.get(OBJECT_EDIT)))
        return td


class ModulatedPolicy(TensorDictSequential):
    """The graph built by :func:`make_policy` (a ``TensorDictSequential``)."""

    def __init__(self, *modules, layout: ModulationLayout, persistent: bool):
        super().__init__(*modules)
        self.layout, self.persistent = layout, persistent

    def primer(self) -> TensorDictPrimer:
        """The state the env must carry for this policy (zeros at reset); empty without persistent R."""
        spec = {}
        if self.persistent:
            spec = {key: Unbounded(shape=shape) for key, shape in EDIT_SHAPES.items()}
        return TensorDictPrimer(Composite(spec), default_value=0.0, expand_specs=True)


def make_policy(tracker, modulator=None, channels=None, config: ModulationConfig = ModulationConfig()) -> ModulatedPolicy:
    """Modulator → R, O → frozen tracker → T as one policy for a plain TrackingEnv.

    Args:
        tracker: the frozen generalist (:class:`adadex.modules.tracker.Tracker`); runs
            deterministically, without gradient, and is frozen by this call.
        modulator: an :class:`adadex.modules.modulator.Modulator`, or ``None`` for the tracker alone.
        channels: the channel set (default: the modulator's); must match the modulator's.
        config: λ's, bounds and persistence — the same values as the transformed env's.
    """
    layout = ModulationLayout(channels if channels is not None else
                              (modulator.layout.channels if modulator is not None else "none"))
    if modulator is None and layout.dim:
        raise ValueError(f"channels {layout.name} need a modulator; pass modulator=… or channels='none'")
    if modulator is not None and modulator.layout.channels != layout.channels:
        raise ValueError(f"the modulator was built for channels {modulator.layout.name}, not {layout.name}")
    chain = modulation(layout.channels, tracker, config)
    persistent = "R" in layout and config.persistent
    modules = []
    if persistent:
        modules.append(_ShowEdit(next(t for t in chain if isinstance(t, ReferenceModulation))))
    if modulator is not None:
        modules.append(getattr(modulator, "actor", modulator))
    modules.append(_TrackerStage(chain, layout, persistent))
    return ModulatedPolicy(*modules, layout=layout, persistent=persistent)
