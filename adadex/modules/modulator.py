"""The modulator: actor + critic that read what the modulator sees and output the modulation.

One flat action in [−1, 1]^D (``"action"``), D set by the channels that are on
(:class:`adadex.modules.channels.ModulationLayout`): a shared trunk and one head per active
channel, in the registry's order and sized by its record (:data:`adadex.modules.channels.CHANNELS`)
— R: reference residuals for the future offsets (hand joints 4×22; object pose 4×6, rotation as a
small rotation vector), O: a latent residual (64), T: an action residual (22).
Heads start near zero, so an untrained modulator's mean leaves the tracker almost untouched, and
each channel explores with its own initial scale (the record's ``init_scale``), sized so that
*sampling* an untrained modulator leaves the tracker's success intact as well.

What it reads (``inputs``):

* ``"view"`` (the default) — ``("modulator", "view")``, :mod:`adadex.modules.modulator_view`: the
  tracker's observation plus the original reference and the errors against it, its accumulated
  edit, the object's start offset, the servo lag, its last action, the episode phase and the
  ``history`` previous frames. The env must carry the view's state:
  ``modulation(channels, tracker, view=modulator.view)`` for training, or
  :func:`adadex.transforms.policy.make_policy`'s primer.
* ``"observation"`` — the tracker's 273-D observation alone (checkpoints saved before the view).

Two settings shift the action around a point other than zero (both off by default; both need the view):

* ``prior="anchor"`` — channel C's palm action is an offset around the object anchor's palm shift
  (:meth:`adadex.modules.anchor.ObjectAnchor.palm_shift`: the object's horizontal start offset,
  faded as the reference carries the object), expressed in C's units (÷ ``lambda_palm``). The
  untrained modulator (heads at zero) *is* the anchored feed-forward around the tracker it modulates;
  training learns corrections, including not reaching; ``prior_lookahead`` times its hold and
  release by the reference object at t+1 (default), t+2, t+4 or t+12, as ``Tracker(anchor_lookahead=…)``
  does, and ``prior_reach`` (m, > 0) leaves objects displaced that far or farther where they lie, as
  ``Tracker(anchor_reach=…)`` does (past ~10 cm the paper's thresholds fail a hand that holds the
  object). It reads the view's ``start_offset`` and ``original_future`` and the reference object's
  start, ``("object", "reference_start")`` — the entry the view's start offset and the anchored
  tracker read; nothing the simulator hides.
* ``hold_steps=k`` with ``hold_scale`` — temporally correlated exploration: while the policy samples
  (``ExplorationType.RANDOM``: collectors, ``evaluate(sample=True)``) the chosen channels' action is
  shifted by ``hold_scale · z``, ``z ~ N(0, I)`` drawn at the episode's steps 0, k, 2k, … (the
  view's phase) and held in between, so a tried palm offset lasts k steps; deterministic runs
  (evaluation) use ``z = 0``.

Both are per-sample bounds of the TanhNormal (:class:`ActionShift`, ``make_actor``'s ``bounds``):
the action is ``shift + tanh(N(loc, scale))`` between ``shift ∓ 1``, and the collector stores the
bounds it sampled between, ``("modulator", "low"/"high")``. PPO's loss reads those stored bounds
(:func:`adadex.modules.nets.stored_bounds_actor`), so the ratio π_new/π_old is evaluated at exactly
the shift the action was sampled around. Why the update stays valid with the held noise: ``z`` is an
exogenous process (drawn on a schedule, never from the actions or the parameters), so the trajectory
density factorises as p(z) · Π_t π_θ(a_t | s_t, z_t) · P(s_{t+1} | s_t, a_t), and ∇ log p(τ) = Σ_t
∇ log π_θ(a_t | s_t, z_t): each step's fresh Gaussian given (s_t, z_t) is the policy whose
log-probability PPO evaluates, and its ratio is exact. (Sampling a held Gaussian and scoring it with
the per-step marginal, as gSDE does, is not: given s_t the held noise is not independent of the
state it steered.) The critic does not see ``z``; its value is a baseline, so that biases nothing
beyond what a bootstrapped value already does.

A recurrent core (``core="gru"``, off by default): TorchRL's ``GRUModule`` reads the (normalized) input
at every step and the trunk reads its summary of the episode so far beside it
(:func:`adadex.modules.nets.make_core`), for what a few stacked frames cannot show: how this robot and
this object have answered the tracker over the episode. It carries its hidden state
``("modulator", "core_state")`` in the env as the view does (the trainer's env and
:func:`adadex.transforms.policy.make_policy`'s primer hold it; :func:`adadex.modules.nets.recurrent_state_shapes`
names it), and PPO updates it over whole sequences. Not with ``prior`` or ``hold_steps``.

Decisions every k steps (``decide_every=k``, off by default): the modulator chooses at the episode's
steps 0, k, 2k, … and the env holds that action for the k steps
(:class:`adadex.transforms.modulation.ModulatorView`; the view's ``held`` part says which steps hold).
Between decisions its heads are a fixed N(0, 1) that no parameter moves, so PPO scores one choice per
k steps, each acting long enough for the return to show it — where a per-step edit of a few
hundredths of a radian, redrawn every 83 ms, is lost in the noise of the others (docs/modulation.md).
A held T edits every step's action alike; a held R (persistent) adds its residual to the carried
reference edit at every step, so a decision sets how fast the edit moves for the k steps.

* ``modulator.actor`` — in: its input; out: ``"action"`` (D), ``"action_log_prob"``,
  ``("modulator", "loc")``, ``("modulator", "scale")``.
* ``modulator.critic`` — in: its input; out: ``"state_value"``.

Use it on ``TransformedEnv(TrackingEnv(…), modulation(channels, tracker, view=modulator.view))`` with
any TorchRL loss, or with the tracker in one policy graph via :func:`adadex.transforms.policy.make_policy`.

Example
-------
>>> import torch
>>> from tensordict import TensorDict
>>> mod = Modulator("R+T", hidden=(64, 64), inputs="observation")
>>> mod.layout.dim
134
>>> mod(TensorDict({"observation": torch.zeros(2, 273)}, batch_size=[2]))["action"].shape
torch.Size([2, 134])
>>> Modulator("R+T", hidden=(64, 64)).obs_key, Modulator("R+T", hidden=(64, 64)).view.dim
(('modulator', 'view'), 871)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from tensordict.nn import InteractionType, TensorDictModule
from tensordict.nn.probabilistic import interaction_type
from torch import nn

from adadex.envs.observation import OBS_DIM, OBSERVATION, REF_OBJECT_START, REF_OFFSETS
from adadex.errors import ConfigError, check_number
from adadex.modules.anchor import LOOKAHEADS, ObjectAnchor
from adadex.modules.channels import CHANNELS, PALM, ModulationLayout
from adadex.modules.modulator_view import VIEW, ViewLayout
from adadex.modules.nets import CORES, ActorCritic, make_actor, make_core, make_critic
from adadex.sim.robot import NUM_JOINTS

#: what a modulator may read (see the module docstring)
INPUTS = ("view", "observation")
#: the action's prior mean (see the module docstring): none, or the object anchor's palm shift on channel C
PRIORS = (None, "anchor")
#: the anchor the prior follows: the anchored feed-forward's (``Tracker(residual=…, anchor=0.05)``)
PRIOR_ANCHOR = {"release": 0.05, "hold": 0.02, "reach": 0.0}
_DEFAULT_LAMBDA_PALM = next(f.default for f in CHANNELS["C"].fields if f.name == "lambda_palm")


class ActionShift(nn.Module):
    """(view[, reference object start]) → (shift − 1, shift + 1): the per-sample bounds of the
    modulator's TanhNormal, so its action is ``shift + tanh(·)`` (see the module docstring).

    ``shift`` is zero except C's palm entries under ``prior="anchor"`` (the anchor's palm shift ÷
    ``lambda_palm``) and, while sampling, the held noise of the ``hold`` entries. It holds no
    parameters and no state-dict entries; the held noise (one row per world) is a plain attribute.

    Args:
        layout: the modulator's view layout.
        prior: ``None`` or ``"anchor"``.
        lambda_palm: m per unit of C's palm action (the env's ``ModulationConfig.lambda_palm``).
        hold_steps: k, steps the noise is held (0: no held noise).
        hold_scale: (D,) held-noise scale per flat action entry (0 where none).
        lookahead: the reference frame ahead (one of :data:`~adadex.modules.anchor.LOOKAHEADS`) whose
            object travel times the prior's hold and release, as the env's ``ModulationConfig.reach_lookahead``.
        reach: m; > 0: the prior leaves objects displaced this far or farther unanchored; 0: no limit.
    """

    def __init__(self, layout: ViewLayout, prior: str | None = None, lambda_palm: float = _DEFAULT_LAMBDA_PALM,
                 hold_steps: int = 0, hold_scale: torch.Tensor | None = None, lookahead: int = 1, reach: float = 0.0):
        super().__init__()
        self.prior, self.lambda_palm, self.hold_steps = prior, float(lambda_palm), int(hold_steps)
        part = layout.slices()
        future = part["original_future"]
        self._anchor = ObjectAnchor(**{**PRIOR_ANCHOR, "reach": reach}, lookahead=lookahead) \
            if prior == "anchor" else None
        # original_future holds the joints at t+1, t+2, t+4, t+12, then the object poses at the same frames
        obj = future.start + (len(REF_OFFSETS) - 1) * NUM_JOINTS + 7 * LOOKAHEADS.index(self._anchor.lookahead) \
            if self._anchor is not None else 0
        self._obj_ahead = slice(obj, obj + 3)
        self._offset = slice(part["start_offset"].start, part["start_offset"].start + 2)
        self._phase = part["phase"].start
        self._palm = next((sl for key, sl, _ in layout.channels.segments if key == PALM), None)
        self._dim = layout.action_dim
        self._hold_scale = None if hold_scale is None else hold_scale.detach().clone().float()
        self._held = None            # (…, D) the held noise of each world

    def forward(self, view: torch.Tensor, ref_object_start: torch.Tensor | None = None):
        shift = view.new_zeros(*view.shape[:-1], self._dim)
        if self._anchor is not None:
            travel = torch.linalg.vector_norm(view[..., self._obj_ahead] - ref_object_start[..., :3], dim=-1)
            palm = self._anchor.palm_shift(view[..., self._offset], travel) / self.lambda_palm
            shift = torch.cat([shift[..., :self._palm.start], palm, shift[..., self._palm.stop:]], -1)
        if self.hold_steps and interaction_type() is InteractionType.RANDOM:
            shift = shift + self.held_noise(view) * self._hold_scale.to(view)
        return shift - 1.0, shift + 1.0

    def held_noise(self, view: torch.Tensor) -> torch.Tensor:
        """(…, D) noise held since the world's last step that was a multiple of ``hold_steps``
        (drawn from torch's global generator, so a seeded run draws the same)."""
        steps = torch.round(view[..., self._phase] * 100.0).long()
        held = self._held
        if held is None or held.shape != (*view.shape[:-1], self._dim) or held.device != view.device:
            held = view.new_zeros(*view.shape[:-1], self._dim)
            fresh = torch.ones_like(steps, dtype=torch.bool)
        else:
            fresh = steps % self.hold_steps == 0
        if fresh.any():
            held = torch.where(fresh[..., None], torch.randn(held.shape, dtype=held.dtype, device=held.device), held)
        self._held = held
        return held


def channel_scales(layout: ModulationLayout, init_scale=None) -> dict[str, float]:
    """Each active channel's initial exploration scale: the registry's (``None``), one number for
    all, or ``{channel: scale}`` over the registry's defaults.

    >>> channel_scales(ModulationLayout("R+T"), {"T": 0.2})["T"]
    0.2
    """
    if init_scale is None:
        init_scale = {}
    if isinstance(init_scale, Mapping):
        unknown = sorted(set(init_scale) - set(layout.channels))
        if unknown:
            raise ConfigError(f"Modulator.init_scale: channels {unknown} are not among {layout.name}")
        out = {c.name: float(init_scale.get(c.name, c.init_scale)) for c in layout.records}
    else:
        out = dict.fromkeys(layout.channels, float(init_scale))
    for c, v in out.items():
        check_number(f"Modulator.init_scale[{c}]", v, strict_low=True)
    return out


def checked_focus(focus, layout: ModulationLayout, view: ViewLayout | None,
                  context_free: Sequence[str] = ()) -> dict[str, tuple[str, ...]]:
    """``{channel: view parts}`` (a part or a list of them) checked for a modulator of ``layout`` reading
    ``view`` (``None``: the observation alone): channels it has, not context-free, parts of its view.
    Raises :class:`~adadex.errors.ConfigError` naming what does not fit."""
    focus = {str(c): (parts,) if isinstance(parts, str) else tuple(str(p) for p in parts)
             for c, parts in (focus or {}).items()}
    if not focus:
        return {}
    if view is None:
        raise ConfigError("Modulator(focus=…) reads parts of the view: inputs='view'")
    parts = [name for name, _ in view.parts]
    for c, chosen in focus.items():
        if c not in layout.channels or c in context_free:
            raise ConfigError(f"Modulator.focus: {c!r} is not a channel of {layout.name} that reads the "
                              f"view (context-free: {list(context_free)})")
        unknown = [p for p in chosen if p not in parts]
        if unknown or not chosen:
            raise ConfigError(f"Modulator.focus[{c}]: {unknown or 'no parts'} — the view's parts are {parts}")
    return focus


class Modulator(ActorCritic):
    """Actor + critic with one head per active channel (see the module docstring).

    Args:
        channels: ``"R+O+T"``, ``"R+T"``, … (not ``"none"``: no channel, no modulator).
        hidden: widths of the trunk / critic hidden layers.
        init_scale: initial exploration scale (pre-tanh): ``None`` — each channel's from the registry;
            a number for every channel; or ``{channel: scale}``.
        loc_bound: > 0 bounds the pre-tanh mean to ±loc_bound (see :class:`~adadex.modules.tracker.Tracker`).
        inputs: ``"view"`` or ``"observation"`` (see the module docstring).
        history: previous frames in the view.
        prior: ``None`` or ``"anchor"``: channel C's palm action is an offset around the object
            anchor's palm shift (see the module docstring; needs C and the view).
        lambda_palm: m per unit of C's palm action, as the env's ``ModulationConfig.lambda_palm``
            (the prior is expressed in C's units).
        prior_lookahead: the reference frame ahead (1, 2, 4 or 12) whose object travel times the
            prior's hold and release, as the env's ``ModulationConfig.reach_lookahead`` (default 1).
        prior_reach: m; > 0: the prior leaves objects displaced this far or farther from the
            reference's start where they lie (``Tracker(anchor_reach=…)``); 0 (default): no limit.
        hold_steps: > 0 holds exploration noise for this many steps on the ``hold_scale`` channels
            (see the module docstring; needs the view); 0: off.
        hold_scale: the held noise's scale in action units: a number for every channel, or
            ``{name: scale}`` by channel (``"C"``) or entry (``"palm"``, ``"grip"``, …; an entry's
            own before its channel's); what is left out holds none.
        reach_latched: with channel A (and the view): its reach entry is a fixed N(0, 1) after the
            episode's first step, where the env's ``ModulationConfig.reach_latched`` (the default)
            ignores it — the two must agree. Only the first step's reach is then scored by PPO.
        lead_latched: the same for channel L's lead (the env's ``ModulationConfig.lead_latched``).
        gain_latched: the same for channel K's gains (the env's ``ModulationConfig.gain_latched``).
        context_free: channels whose choice reads no observation — one learned distribution, the same
            in every episode (:class:`~adadex.modules.nets.GaussianHeads`' ``blind`` heads), e.g.
            ``("K",)``: a robot's servo gains, chosen at the episode's first step where nothing of its
            dynamics shows yet; the critic still reads the view. Default none.
        context_free_rate: how fast such a choice learns: its head's bias enters × this
            (:class:`~adadex.modules.nets.GaussianHeads`' ``blind_rate``; default 30).
        focus: ``{channel: view parts}`` — channels whose head reads only those parts of the view,
            through a small trunk of its own (:class:`~adadex.modules.nets.GaussianHeads`' ``focus``),
            e.g. ``{"A": ["start_offset"]}``: whether to reach for the object, from where it lies.
            Needs the view; default none.
        core: ``"gru"``: a recurrent core over the input (see the module docstring); ``None`` (default): none.
        core_size: the core's hidden size (default 128).
        decide_every: k > 1: the modulator decides at the episode's steps 0, k, 2k, … and its action holds
            for the k steps (see the module docstring; needs the view, not with ``prior`` or ``hold_steps``);
            1 (default): every step.
    """

    kind = "modulator"

    def __init__(self, channels="R+O+T", hidden: Sequence[int] = (512, 256, 128), init_scale=None,
                 loc_bound: float = 0.0, inputs: str = "view", history: int = 3, prior: str | None = None,
                 lambda_palm: float = _DEFAULT_LAMBDA_PALM, hold_steps: int = 0, hold_scale=None,
                 prior_lookahead: int = 1, prior_reach: float = 0.0, reach_latched: bool = True,
                 lead_latched: bool = True, gain_latched: bool = True,
                 context_free: Sequence[str] = (), context_free_rate: float = 30.0,
                 focus: Mapping[str, Sequence[str]] | None = None, core: str | None = None, core_size: int = 128,
                 decide_every: int = 1):
        super().__init__()
        self.layout = ModulationLayout(channels)
        if not self.layout.dim:
            raise ConfigError("a Modulator needs at least one channel (R, O or T); for 'none' use the tracker alone")
        check_number("Modulator.loc_bound", loc_bound)
        if inputs not in INPUTS:
            raise ConfigError(f"Modulator.inputs must be one of {INPUTS}, got {inputs!r}")
        scales = channel_scales(self.layout, init_scale)
        check_number("Modulator.decide_every", decide_every, low=1, integer=True)
        if decide_every > 1 and inputs != "view":
            raise ConfigError(f"Modulator(decide_every={decide_every}) reads when it decides from the view: inputs='view'")
        self.view = ViewLayout(self.layout.channels, history, decide_every) if inputs == "view" else None
        self.obs_key, obs_dim = (VIEW, self.view.dim) if self.view is not None else (OBSERVATION, OBS_DIM)
        shift, held = self._shift(prior, lambda_palm, hold_steps, hold_scale, prior_lookahead, prior_reach)
        self.config = {"channels": self.layout.name, "hidden": list(hidden), "init_scale": scales,
                       "loc_bound": float(loc_bound), "inputs": inputs, "history": int(history)}
        if shift is not None:         # only then: checkpoints without these settings keep their config
            self.config.update(prior=prior, lambda_palm=float(lambda_palm), hold_steps=int(hold_steps),
                               hold_scale=held)
        if prior is not None and prior_lookahead != 1:      # the same: saved priors read t+1
            self.config["prior_lookahead"] = int(prior_lookahead)
        if prior_reach > 0:                                  # the same: saved priors reach everywhere
            self.config["prior_reach"] = float(prior_reach)
        switches = {"reach_latched": reach_latched, "lead_latched": lead_latched, "gain_latched": gain_latched}
        fixed = []                       # entries the env ignores after the episode's first step
        for record in self.layout.records:
            if record.latch:             # only then: checkpoints without the channel keep their config
                switch = self.config[record.latch] = bool(switches[record.latch])
                if switch and self.view is not None:
                    for key, sl, _ in self.layout.segments:
                        if key in record.keys:
                            fixed += range(sl.start, sl.stop)
        latched = [(self.view.slices()["phase"].start, fixed)] if fixed else []
        if decide_every > 1:             # between decisions the env holds the last action: no entry acts
            if shift is not None:
                raise ConfigError("Modulator(decide_every=…) cannot be combined with prior=… or hold_steps=… "
                                  "(per-sample bounds)")
            latched.append((self.view.slices()["held"].start, range(self.layout.dim)))
            self.config["decide_every"] = int(decide_every)     # only then: saved configs stay as they were
        context_free = tuple(dict.fromkeys(str(c) for c in context_free))
        unknown = [c for c in context_free if c not in self.layout.channels]
        if unknown:
            raise ConfigError(f"Modulator.context_free: channels {unknown} are not among {self.layout.name}")
        if context_free:                 # only then: checkpoints without it keep their config
            self.config.update(context_free=list(context_free), context_free_rate=float(context_free_rate))
        focus = checked_focus(focus, self.layout, self.view, context_free)
        if focus:                        # only then: checkpoints without it keep their config
            self.config["focus"] = {c: list(parts) for c, parts in focus.items()}
        part = self.view.slices() if focus else {}
        if core not in CORES:
            raise ConfigError(f"Modulator.core must be one of {CORES}, got {core!r}")
        check_number("Modulator.core_size", core_size, strict_low=True, integer=True)
        if core is not None:
            if shift is not None:
                raise ConfigError("Modulator(core=…) cannot be combined with prior=… or hold_steps=… (per-sample bounds)")
            self.config.update(core=core, core_size=int(core_size))    # only then: saved configs stay as they were
        self.actor = make_actor(self.obs_key, obs_dim, self.layout.channel_sizes, -1.0, 1.0, hidden,
                                namespace="modulator", init_scale=[scales[c] for c in self.layout.channels],
                                loc_bound=loc_bound, bounds=shift, latched=latched or None,
                                blind=[self.layout.channels.index(c) for c in context_free],
                                blind_rate=context_free_rate,
                                focus={self.layout.channels.index(c): [j for p in parts for j in
                                                                       range(part[p].start, part[p].stop)]
                                       for c, parts in focus.items()},
                                core=None if core is None else make_core(self.obs_key, obs_dim, core_size,
                                                                         namespace="modulator"),
                                core_dim=int(core_size) if core is not None else 0)
        self.critic = make_critic(self.obs_key, obs_dim, hidden)

    def _shift(self, prior, lambda_palm, hold_steps, hold_scale, lookahead=1, reach=0.0):
        """The :class:`ActionShift` bounds module and the held scales per channel, or (None, {})."""
        if prior not in PRIORS:
            raise ConfigError(f"Modulator.prior must be one of {PRIORS}, got {prior!r}")
        if lookahead not in LOOKAHEADS or isinstance(lookahead, bool):
            raise ConfigError(f"Modulator.prior_lookahead must be one of the observation's reference frames ahead "
                              f"{LOOKAHEADS}, got {lookahead!r}")
        check_number("Modulator.lambda_palm", lambda_palm, strict_low=True)
        check_number("Modulator.hold_steps", hold_steps, integer=True)
        check_number("Modulator.prior_reach", reach)
        if reach > 0 and prior != "anchor":
            raise ConfigError(f"Modulator(prior_reach={reach}) limits the anchor prior, which is off (prior={prior!r})")
        if prior == "anchor" and "C" not in self.layout:
            raise ConfigError(f"Modulator(prior='anchor') shifts channel C's palm, which {self.layout.name} lacks")
        if hold_scale is None:
            held = {}
        elif isinstance(hold_scale, Mapping):
            held = {str(k): float(v) for k, v in hold_scale.items()}
        else:
            held = dict.fromkeys(self.layout.channels, float(hold_scale))
        entries = {key[-1]: c.name for c in self.layout.records for key in c.keys}    # e.g. "palm" → "C"
        unknown = sorted(set(held) - set(self.layout.channels) - set(entries))
        if unknown:
            raise ConfigError(f"Modulator.hold_scale: {unknown} are neither channels of {self.layout.name} nor "
                              f"their entries {sorted(entries)}")
        for c, v in held.items():
            check_number(f"Modulator.hold_scale[{c}]", v)
        if bool(hold_steps) != any(v > 0 for v in held.values()):
            raise ConfigError(f"Modulator: hold_steps={hold_steps} and hold_scale={hold_scale!r} go together "
                              "(held noise needs both > 0; off: hold_steps=0, hold_scale=None)")
        if prior is None and not hold_steps:
            return None, {}
        if self.view is None:
            raise ConfigError("Modulator(prior=…/hold_steps=…) reads the view: inputs='view'")
        scale = torch.zeros(self.layout.dim)
        for key, sl, _ in self.layout.segments:         # an entry's own scale before its channel's
            scale[sl] = held.get(key[-1], held.get(entries[key[-1]], 0.0))
        keys = [VIEW] + ([REF_OBJECT_START] if prior == "anchor" else [])
        module = ActionShift(self.view, prior, lambda_palm, hold_steps, scale if hold_steps else None, lookahead, reach)
        return TensorDictModule(module, in_keys=keys, out_keys=[("modulator", "low"), ("modulator", "high")]), held

    @property
    def channels(self) -> tuple[str, ...]:
        return self.layout.channels

    @property
    def heads(self):
        """The actor's :class:`~adadex.modules.nets.GaussianHeads` (normalizer, trunk, one head per channel)."""
        return self.actor._sampling_parts[0]

    def context_free_actions(self) -> dict[str, list[float]]:
        """The deterministic action of each context-free channel's entries (``tanh`` of the learned
        mean, in [−1, 1]; the same for every observation), by entry name, e.g. ``{"gain": [arm, hand]}``;
        empty when no channel is context-free."""
        net = self.heads
        out = {}
        for c in self.config.get("context_free", ()):
            head = net.heads[self.layout.channels.index(c)]
            loc = torch.tanh(net.blind_rate * head.bias.detach()[:head.out_features // 2])
            first = min(sl.start for key, sl, _ in self.layout.segments if key in CHANNELS[c].keys)
            for key, sl, _ in self.layout.segments:
                if key in CHANNELS[c].keys:
                    out[key[-1]] = loc[sl.start - first:sl.stop - first].tolist()
        return out

    @classmethod
    def upgrade_config(cls, config: dict) -> dict:
        """Checkpoints saved before the view read the tracker's observation alone."""
        config.setdefault("inputs", "observation")
        config.setdefault("history", 3)
        return config
