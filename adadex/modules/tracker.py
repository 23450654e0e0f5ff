"""The tracker: actor + critic reading the paper's 273-D observation, writing a 22-D joint-target change.

Specialists (one per semantic group), the behaviour-cloned generalist and the vanilla-PPO baseline
are all this one class; they differ only in what they were trained on.

* ``tracker.actor`` — :class:`torchrl.modules.ProbabilisticActor`, ``TanhNormal`` over 22-D within
  ±``max_action`` (the env's action bound). in: ``"observation"`` (273-D, assembled by
  :func:`adadex.envs.observation.flat_observation`); out: ``"action"``, ``"action_log_prob"``,
  ``("tracker", "loc")``, ``("tracker", "scale")``. It samples under
  ``set_exploration_type(ExplorationType.RANDOM)`` (what TorchRL's collectors set); otherwise —
  TorchRL's default, used for evaluation and behaviour cloning — the action is the deterministic
  ``max_action·tanh(loc)``.
* ``tracker.critic`` — :class:`torchrl.modules.ValueOperator`; in: ``"observation"``; out: ``"state_value"``.

The tracker never knows whether it is being modulated: the modulation transforms edit the
structured entries and reassemble ``"observation"`` with the same function before it reads it.

Example
-------
>>> import torch
>>> from tensordict import TensorDict
>>> tracker = Tracker(hidden=(64, 64))
>>> td = tracker(TensorDict({"observation": torch.zeros(4, 273)}, batch_size=[4]))
>>> td["action"].shape, bool((td["action"].abs() <= 0.1).all())
(torch.Size([4, 22]), True)
"""

from __future__ import annotations

from collections.abc import Sequence

from adadex.envs.observation import OBS_DIM, OBSERVATION
from adadex.modules.nets import ActorCritic, make_actor, make_critic
from adadex.sim.robot import NUM_JOINTS


class Tracker(ActorCritic):
    """Actor + critic over the 273-D observation (see the module docstring).

    Args:
        hidden: widths of the actor's and critic's hidden layers.
        max_action: bound of the joint-target change, rad (``TrackingConfig.max_action``).
        init_scale: initial exploration scale (pre-tanh) of the Gaussian.
    """

    kind = "tracker"

    def __init__(self, hidden: Sequence[int] = (512, 256, 128), max_action: float = 0.1, init_scale: float = 1.0):
        super().__init__()
        if not max_action > 0:
            raise ValueError(f"max_action must be > 0, got {max_action}")
        self.config = {"hidden": list(hidden), "max_action": float(max_action), "init_scale": float(init_scale)}
        self.actor = make_actor(OBSERVATION, OBS_DIM, [NUM_JOINTS], -max_action, max_action, hidden,
                                namespace="tracker", init_scale=init_scale)
        self.critic = make_critic(OBSERVATION, OBS_DIM, hidden)

