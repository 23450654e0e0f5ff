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

**Residual tracking** (``residual > 0``, what the training recipes use): the action is the kinematic
replay's, ``q̂_{t+1} − q_target`` (the next reference joints from the observation minus the current
joint targets ``("proprio", "joint_target")``), plus a learned correction within ±``residual``. An
untrained residual tracker *is* kinematic replay, so PPO explores around the replay floor instead of
from scratch (as residual trackers do); the correction is a TanhNormal between the feed-forward ∓
``residual``, so its log-probability is exact for PPO and behaviour cloning clones the whole action.

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

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from adadex.envs.observation import JOINT_TARGET, NEXT_REF_JOINTS as _NEXT_REF, OBJECT_START, OBS_DIM, OBSERVATION, \
    REF_OBJECT_START
from adadex.errors import ConfigError, check_number
from adadex.modules.anchor import ObjectAnchor
from adadex.modules.nets import ActorCritic, make_actor, make_critic
from adadex.sim.robot import NUM_JOINTS



class ReplayBounds(nn.Module):
    """(observation, joint target[, object start, reference object start]) → (feed-forward − r,
    feed-forward + r), the feed-forward being kinematic replay's action: the reference joints at t+1
    (read from the flat observation, so a modulated reference moves it too) minus the current joint
    targets; with an ``anchor`` (:class:`~adadex.modules.anchor.ObjectAnchor`), of the reference
    shifted onto the object where it started the episode.

    Args:
        residual: the half-width ``r`` of the bounds around the feed-forward, rad.
        anchor: the object anchor shifting the replayed reference (None: plain replay). With one,
            ``forward`` needs the object's and the reference object's start poses.
    """

    def __init__(self, residual: float, anchor: ObjectAnchor | None = None):
        super().__init__()
        self.residual = float(residual)
        self.anchor = anchor

    def forward(self, observation: torch.Tensor, joint_target: torch.Tensor, object_start: torch.Tensor | None = None,
                ref_object_start: torch.Tensor | None = None):
        ff = observation[..., _NEXT_REF] - joint_target
        if self.anchor is not None:
            ff = ff + self.anchor(observation, object_start, ref_object_start)
        return ff - self.residual, ff + self.residual


class Tracker(ActorCritic):
    """Actor + critic over the 273-D observation (see the module docstring).

    Args:
        hidden: widths of the actor's and critic's hidden layers.
        max_action: bound of the joint-target change, rad (``TrackingConfig.max_action``).
        init_scale: initial exploration scale (pre-tanh) of the Gaussian.
        residual: 0 — the action is ``max_action·tanh(·)`` of the network; > 0 — kinematic replay's
            action plus a learned correction within ±``residual`` rad (see the module docstring);
            the actor then also reads ``("proprio", "joint_target")``.
        loc_bound: > 0 bounds the Gaussian's pre-tanh mean to ±loc_bound (see
            :func:`~adadex.modules.nets.make_actor`); 0, the default of checkpoints saved before it
            existed, leaves it unbounded.
        anchor: > 0 (needs ``residual > 0``) anchors the feed-forward to the object
            (:class:`~adadex.modules.anchor.ObjectAnchor` with ``release=anchor`` m): replay of the
            reference shifted onto where the object started the episode, fading out as the reference
            carries the object; the actor then also reads ``("object", "start_pose")`` and
            ``("object", "reference_start")``. 0 (default): plain replay.
        anchor_reach: > 0 (needs ``anchor``) leaves objects displaced this far (m) or farther
            unanchored (``ObjectAnchor(reach=…)``); 0 (default): no limit.
        anchor_iterations: Gauss–Newton steps of the anchor's palm shift (``ObjectAnchor(iterations=…)``;
            3 by default; checkpoints saved before it existed load with 1, the step they used).
        anchor_lookahead: control steps ahead at which the anchor reads the reference object's travel
            (``ObjectAnchor(lookahead=…)``: 1, 2, 4 or 12; default 1, what checkpoints saved before it
            existed used); needs ``anchor`` when not 1.
        torchrl_tanh_loc: bound the mean as checkpoints saved before 2026-11-25 did (see
            :func:`~adadex.modules.nets.make_actor`: for a residual tracker TorchRL's ``tanh_loc``
            also shifted the mean by the feed-forward); :meth:`load` sets it for those checkpoints.
    """

    kind = "tracker"

    def __init__(self, hidden: Sequence[int] = (512, 256, 128), max_action: float = 0.1, init_scale: float = 1.0,
                 residual: float = 0.0, loc_bound: float = 0.0, anchor: float = 0.0, anchor_reach: float = 0.0,
                 anchor_iterations: int = 3, torchrl_tanh_loc: bool = False, anchor_lookahead: int = 1):
        super().__init__()
        check_number("Tracker.max_action", max_action, strict_low=True)
        check_number("Tracker.residual", residual)
        check_number("Tracker.loc_bound", loc_bound)
        check_number("Tracker.anchor", anchor)
        check_number("Tracker.anchor_reach", anchor_reach)
        check_number("Tracker.anchor_iterations", anchor_iterations, low=1, integer=True)
        if anchor_reach > 0 and not anchor > 0:
            raise ConfigError(f"Tracker(anchor_reach={anchor_reach}) limits the object anchor, which is off; "
                              f"set anchor > 0")
        if anchor_lookahead != 1 and not anchor > 0:
            raise ConfigError(f"Tracker(anchor_lookahead={anchor_lookahead}) times the object anchor, which is off; "
                              f"set anchor > 0")
        if anchor > 0 and not residual > 0:
            raise ConfigError(f"Tracker(anchor={anchor}) anchors the replay feed-forward, which only a residual "
                              f"tracker has; set residual > 0")
        self.config = {"hidden": list(hidden), "max_action": float(max_action), "init_scale": float(init_scale),
                       "residual": float(residual), "loc_bound": float(loc_bound), "anchor": float(anchor),
                       "anchor_reach": float(anchor_reach), "anchor_iterations": int(anchor_iterations),
                       "torchrl_tanh_loc": bool(torchrl_tanh_loc)}
        if anchor_lookahead != 1:     # at its default the config reads as before it existed (stamps, fingerprints)
            self.config["anchor_lookahead"] = int(anchor_lookahead)
        bounds = None
        if residual > 0:
            keys = [OBSERVATION, JOINT_TARGET] + ([OBJECT_START, REF_OBJECT_START] if anchor > 0 else [])
            anchored = ObjectAnchor(anchor, reach=anchor_reach, iterations=anchor_iterations,
                                    lookahead=anchor_lookahead) if anchor > 0 else None
            bounds = TensorDictModule(ReplayBounds(residual, anchored),
                                      in_keys=keys, out_keys=[("tracker", "low"), ("tracker", "high")])
        self.actor = make_actor(OBSERVATION, OBS_DIM, [NUM_JOINTS], -max_action, max_action, hidden,
                                namespace="tracker", init_scale=init_scale, bounds=bounds, loc_bound=loc_bound,
                                torchrl_tanh_loc=torchrl_tanh_loc)
        self.critic = make_critic(OBSERVATION, OBS_DIM, hidden)

    @classmethod
    def from_config(cls, config, max_action: float | None = None) -> Tracker:
        """The tracker a :class:`~adadex.train.config.PolicyConfig` describes (what the training recipes
        train: ``Tracker.from_config(PolicyConfig())``); the constructor's own defaults describe a plain
        tracker (no residual, no anchor). ``max_action``: the env's action bound (default the
        constructor's).

        >>> from adadex.train.config import PolicyConfig
        >>> Tracker.from_config(PolicyConfig(hidden=(32,))).config["residual"]
        0.25
        """
        extra = {} if max_action is None else {"max_action": max_action}
        return cls(hidden=config.hidden, init_scale=config.init_scale, residual=config.residual,
                   loc_bound=config.loc_bound, anchor=config.anchor, anchor_reach=config.anchor_reach,
                   anchor_iterations=config.anchor_iterations, anchor_lookahead=config.anchor_lookahead, **extra)

    @classmethod
    def replay(cls, hidden: Sequence[int] = (16,), max_action: float = 0.1, residual: float = 0.25) -> Tracker:
        """Kinematic replay as a tracker: a residual tracker whose correction is exactly zero (its
        heads zeroed), so its deterministic action is replay's (to float32 rounding). A frozen
        tracker to modulate without training one first, e.g. the cheap check that a modulator
        setting can learn.

        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = TensorDict({"observation": torch.rand(3, 273) * 0.1, ("proprio", "joint_target"): torch.zeros(3, 22)},
        ...                  batch_size=[3])
        >>> from adadex.envs.observation import NEXT_REF_JOINTS
        >>> float((Tracker.replay()(obs)["action"] - obs["observation"][:, NEXT_REF_JOINTS]).abs().max()) < 1e-6
        True
        """
        return cls(hidden=hidden, max_action=max_action, residual=residual).zero_mean().freeze()

    @classmethod
    def upgrade_config(cls, config: dict) -> dict:
        """Checkpoints saved before ``torchrl_tanh_loc`` existed bounded their mean with TorchRL's
        ``tanh_loc`` (it makes a difference only with ``residual`` and ``loc_bound`` both > 0); those
        saved before ``anchor_iterations`` placed the anchored palm with one linearized step."""
        config.setdefault("torchrl_tanh_loc", float(config.get("loc_bound", 0.0)) > 0)
        config.setdefault("anchor_iterations", 1)          # the anchor's single linearized step before 2026-11-26
        return config

