"""Network pieces shared by the tracker and the modulator: observation normalization, a Gaussian
policy body with one or more heads, a value body, and the TorchRL actor/critic built from them.

The actor is a :class:`torchrl.modules.ProbabilisticActor` with a ``TanhNormal`` between ``low``
and ``high``: it samples under ``ExplorationType.RANDOM`` (set by TorchRL's collectors for
training) and otherwise returns the deterministic ``tanh(loc)`` (evaluation, behaviour cloning). The critic is a
:class:`torchrl.modules.ValueOperator`. Both read one flat observation key and normalize it with
their own :class:`Normalizer`, so a saved module carries its statistics.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from tensordict.nn import (InteractionType, NormalParamExtractor, TensorDictModule, TensorDictModuleBase,
                           TensorDictSequential)
from tensordict.nn.probabilistic import interaction_type
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import MLP, GRUModule, LSTMModule, ProbabilisticActor, TanhNormal, ValueOperator

from adadex.errors import ArrayError, CheckpointError, ConfigError, ConfigTypeError, check_number
from adadex.io import atomic_write


class Normalizer(nn.Module):
    """``(x − loc) / scale``, clipped to ±``clip``; identity until :meth:`fit` sets the statistics.

    The statistics are buffers: they travel with ``state_dict`` and never receive gradients.

    Args:
        dim: the size of the last dimension it normalizes.
        clip: the output's bound (default 10).
        eps: a standard deviation at or below it gives scale 1 (default 1e-3).

    Examples:
        >>> norm = Normalizer(2).fit(torch.tensor([[0.0, 5.0], [2.0, 5.0]]))
        >>> norm(torch.tensor([[1.0, 5.0]]))
        tensor([[0., 0.]])
    """

    def __init__(self, dim: int, clip: float = 10.0, eps: float = 1e-3):
        super().__init__()
        self.register_buffer("loc", torch.zeros(dim))
        self.register_buffer("scale", torch.ones(dim))
        self.clip, self.eps = clip, eps

    @torch.no_grad()
    def fit(self, samples: torch.Tensor) -> Normalizer:
        """Set loc/scale to the mean and standard deviation of ``samples`` (…, dim); constant
        entries (the std below ``eps``) get scale 1 so they pass unchanged up to the shift."""
        x = samples.reshape(-1, samples.shape[-1]).to(self.loc.dtype)
        if x.shape[0] < 2 or not torch.isfinite(x).all():
            raise ArrayError(f"Normalizer.fit needs ≥ 2 finite samples, got shape {tuple(samples.shape)}")
        return self.set_statistics(x.mean(0), x.std(0))

    @torch.no_grad()
    def set_statistics(self, mean: torch.Tensor, std: torch.Tensor) -> Normalizer:
        """Normalize with ``mean`` and ``std`` ((dim,)); entries with ``std`` below ``eps`` get scale 1."""
        std = std.to(self.scale.dtype)
        self.loc.copy_(mean.to(self.loc.dtype))
        self.scale.copy_(torch.where(std > self.eps, std, torch.ones_like(std)))
        return self

    @property
    def fitted(self) -> bool:
        """Whether statistics were set (an unfitted normalizer is the identity: loc 0, scale 1)."""
        return bool((self.loc != 0).any() or (self.scale != 1).any())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.loc) / self.scale).clamp(-self.clip, self.clip)


class GaussianHeads(nn.Module):
    """obs → (loc, scale): a shared trunk, then one linear head per output group, concatenated in
    order. The last layers start small (``init_gain``) so the initial mean action is near 0.
    ``init_scale`` is the initial exploration scale, one for all heads or one per head (the
    modulator sizes each channel's own).

    ``latched = (i, entries)`` (optional): where ``obs[..., i] > 0`` the ``entries`` (a slice or a
    list of indices of the output) are a fixed N(0, 1) that no parameter moves — entries the environment ignores there (a
    choice it latched earlier, e.g. channel A's reach after the episode's first step). Their samples
    then carry no parameter's log-probability, so PPO's ratio and gradient come only from the entries
    that act, instead of from noise the environment throws away. A list of such pairs applies each
    (e.g. A's reach after the first step, and every entry between a modulator's decisions).

    ``blind`` (optional): indices of heads that read no observation — their loc and scale are
    ``blind_rate ·`` the head's bias, one learned distribution for every input (the weights stay,
    unused, so the state dict is the same). For a choice that is the robot's and not the moment's
    (channel K's gains, latched at an episode's first step, where nothing the robot does is visible
    yet): a few hundred episodes teach one value, where a trunk over the view fits their noise.
    Why the rate: Adam moves each parameter by about its learning rate a step, whatever the
    gradient's size, so a lone bias moves its output far slower than a trunk of thousands of
    parameters moves its own; at PPO's 3e-4 a K head's bias ended 250 k frames at a gain of 0.03,
    and ×30 at the arm gain a fixed-gain sweep finds best (docs/sim2real.md).

    ``extra_dim`` (optional): features read beside the normalized observation, not normalized — a
    recurrent core's summary of the episode so far (:func:`make_actor`'s ``core``): the trunk reads
    ``[norm(obs), extra]``; ``forward(obs, extra)``.

    ``focus`` (optional): ``{head index: observation indices}`` — heads that read only those entries
    of the (normalized) observation, through a small trunk of their own (``focus_hidden``). For a
    choice that depends on a few numbers the policy can see (channel A's reach on the object's start
    offset): a trunk over the whole view fits the noise of the few hundred choices PPO sees in a run,
    a small one over the relevant entries cannot.

    Args:
        obs_dim: the observation's size (normalized by a :class:`Normalizer` first).
        head_sizes: output entries of each head; loc and scale are (…, sum(head_sizes)).
        hidden: the trunk's widths (its last is the heads' input).
        init_gain: orthogonal-init gain of the heads' weights (default 0.01).
        init_scale: initial exploration scale, one for all heads or one per head (default 1.0).
        activation: the trunk's activation class (default ``nn.ELU``).
        loc_bound: > 0: ``loc = b·tanh(loc/b)`` (default 0: unbounded).
        latched: ``(i, entries)`` (above), a list of them, or None.
        blind: indices of the heads that read no observation (above; default none).
        blind_rate: their bias's scale (above; default 30).
        focus: ``{head index: observation indices}`` read by those heads alone (above; default none).
        focus_hidden: the widths of each focused head's own trunk (default (32, 32)).
        extra_dim: features the trunk reads beside the normalized observation (above; default 0: none).
    """

    def __init__(self, obs_dim: int, head_sizes: Sequence[int], hidden: Sequence[int], *,
                 init_gain: float = 0.01, init_scale: float | Sequence[float] = 1.0, activation=nn.ELU,
                 loc_bound: float = 0.0, latched=None,
                 blind: Sequence[int] = (), blind_rate: float = 30.0,
                 focus: Mapping[int, Sequence[int]] | None = None, focus_hidden: Sequence[int] = (32, 32),
                 extra_dim: int = 0):
        super().__init__()
        self.extra_dim = int(check_number("GaussianHeads extra_dim", extra_dim, integer=True))
        self.blind = frozenset(int(i) for i in blind)
        self.blind_rate = float(check_number("GaussianHeads blind_rate", blind_rate, strict_low=True))
        if not self.blind <= set(range(len(head_sizes))):
            raise ConfigError(f"GaussianHeads: blind heads {sorted(self.blind)} are not among 0…{len(head_sizes) - 1}")
        focus = {int(i): [int(j) for j in idx] for i, idx in (focus or {}).items()}
        bad = sorted(i for i in focus if not 0 <= i < len(head_sizes) or i in self.blind)
        if bad:
            raise ConfigError(f"GaussianHeads: focused heads {bad} are not among 0…{len(head_sizes) - 1} or are blind")
        for i, idx in focus.items():
            if not idx or not all(0 <= j < obs_dim for j in idx):
                raise ConfigError(f"GaussianHeads: head {i}'s focus must be observation indices in 0…{obs_dim - 1}")
        self.focus_nets = nn.ModuleDict({
            str(i): MLP(in_features=len(idx), out_features=focus_hidden[-1], num_cells=list(focus_hidden[:-1]),
                        activation_class=activation, activate_last_layer=True) for i, idx in focus.items()})
        for i, idx in focus.items():      # not persistent: the config rebuilds them
            self.register_buffer(f"focus_index_{i}", torch.tensor(idx, dtype=torch.long), persistent=False)
        self.loc_bound = float(loc_bound)
        rules = [] if latched is None else [latched] if isinstance(latched[0], int) else list(latched)
        self.latched = [int(i) for i, _ in rules]
        for n, (_, entries) in enumerate(rules):   # not persistent: the state dict is the same with or without them
            mask = torch.zeros(sum(head_sizes), dtype=torch.bool)
            mask[entries if isinstance(entries, slice) else list(entries)] = True
            self.register_buffer(f"latched_entries_{n}", mask, persistent=False)
        self.norm = Normalizer(obs_dim)
        self.trunk = MLP(in_features=obs_dim + self.extra_dim, out_features=hidden[-1], num_cells=list(hidden[:-1]),
                         activation_class=activation, activate_last_layer=True)
        self.heads = nn.ModuleList(nn.Linear(focus_hidden[-1] if i in focus else hidden[-1], 2 * n)
                                   for i, n in enumerate(head_sizes))
        for h in self.heads:
            nn.init.orthogonal_(h.weight, gain=init_gain)
            nn.init.zeros_(h.bias)
        scales = [init_scale] * len(head_sizes) if isinstance(init_scale, (int, float)) else list(init_scale)
        if len(scales) != len(head_sizes):
            raise ConfigError(f"GaussianHeads: {len(scales)} initial scales for {len(head_sizes)} heads")
        # parameter-free: the state dict is the same whatever the scales
        self.extracts = [NormalParamExtractor(scale_mapping=f"biased_softplus_{float(s)}") for s in scales]
        self.head_sizes = tuple(head_sizes)

    def _head_input(self, i: int, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        if str(i) in self.focus_nets:
            return self.focus_nets[str(i)](x[..., getattr(self, f"focus_index_{i}")])
        return z

    def forward(self, obs: torch.Tensor, extra: torch.Tensor | None = None):
        x = self.norm(obs)
        z = self.trunk(torch.cat([x, extra], -1) if self.extra_dim else x)
        locs, scales = zip(*(extract(self.blind_rate * h.bias.expand(*z.shape[:-1], -1) if i in self.blind
                                     else h(self._head_input(i, x, z)))
                             for i, (extract, h) in enumerate(zip(self.extracts, self.heads))))
        loc = torch.cat(locs, -1)
        if self.loc_bound > 0:
            loc = self.loc_bound * torch.tanh(loc / self.loc_bound)
        scale = torch.cat(scales, -1)
        if self.latched:
            fixed = functools.reduce(torch.logical_or, (getattr(self, f"latched_entries_{n}") & (obs[..., i:i + 1] > 0)
                                                        for n, i in enumerate(self.latched)))
            loc = torch.where(fixed, torch.zeros_like(loc), loc)
            scale = torch.where(fixed, torch.ones_like(scale), scale)
        return loc, scale


#: the recurrent cores a policy body may have (``None``: none; ``"gru"``: :func:`make_core`)
CORES = (None, "gru")


def make_core(obs_key, obs_dim: int, size: int, *, namespace: str) -> TensorDictSequential:
    """A recurrent core: a :class:`Normalizer` of ``obs_key``, then TorchRL's ``GRUModule`` over it,
    writing its summary of the episode so far, ``(namespace, "memory")`` (``size``), and carrying its
    hidden state ``(namespace, "core_state")`` (1 × ``size``) from step to step, reset where the env
    marks ``"is_init"`` (an episode's first frame; :class:`~adadex.envs.tracking.TrackingEnv` writes it).

    Why a core beside the stacked frames a view may hold: a few frames show what moved, not how the
    robot and object have answered over the episode (a slipping grasp, a servo that lags), which is
    what a policy needs to infer dynamics it cannot observe (the paper's Sec. 3.2). Step by step (a
    collector, ``env.rollout``) the env must carry the state —
    :func:`recurrent_state_shapes` names it, and the trainer and :func:`~adadex.transforms.policy.make_policy`'s
    primer add it; over a batch of whole sequences (a PPO update) run it under
    ``torchrl.modules.set_recurrent_mode(True)``, which starts each sequence from its stored state.

    Args:
        obs_key: the key of the flat observation it reads.
        obs_dim: the observation's size.
        size: the GRU's hidden size (the memory's size).
        namespace: the key prefix of its entries.

    >>> import torch
    >>> from tensordict import TensorDict
    >>> core = make_core("obs", 4, 8, namespace="p")
    >>> td = TensorDict({"obs": torch.zeros(3, 4), "p": {"core_state": torch.zeros(3, 1, 8)},
    ...                  "is_init": torch.ones(3, 1, dtype=torch.bool)}, [3])
    >>> core(td)["p", "memory"].shape, td["next", "p", "core_state"].shape
    (torch.Size([3, 8]), torch.Size([3, 1, 8]))
    """
    check_number("make_core size", size, strict_low=True, integer=True)
    hidden = (namespace, "core_input")
    state = (namespace, "core_state")
    return TensorDictSequential(
        TensorDictModule(Normalizer(obs_dim), in_keys=[obs_key], out_keys=[hidden]),
        GRUModule(input_size=obs_dim, hidden_size=int(size), in_keys=[hidden, state, "is_init"],
                  out_keys=[(namespace, "memory"), ("next", *state)]))


def recurrent_state_shapes(module: nn.Module) -> dict:
    """``{key: shape}`` of the state every TorchRL ``GRUModule`` / ``LSTMModule`` inside ``module`` carries
    from step to step (without the batch dimensions): what an env must prime, zeroed at reset, for the
    module to run step by step. Empty for a feed-forward module.

    Args:
        module: any module (an actor, a critic, a whole policy).

    >>> recurrent_state_shapes(make_core("obs", 4, 8, namespace="p"))
    {('p', 'core_state'): (1, 8)}
    """
    shapes = {}
    for m in module.modules():
        if isinstance(m, (GRUModule, LSTMModule)):
            primers = m.make_tensordict_primer().primers
            for key in primers.keys(True, True):
                shapes[key] = tuple(primers[key].shape)
    return shapes


def make_actor(obs_key, obs_dim: int, head_sizes: Sequence[int], low: float, high: float, hidden: Sequence[int], *,
               namespace: str, action_key="action", init_scale: float | Sequence[float] = 1.0,
               bounds: TensorDictModule | None = None, loc_bound: float = 0.0,
               torchrl_tanh_loc: bool = False, latched=None,
               blind: Sequence[int] = (), blind_rate: float = 30.0,
               focus: Mapping[int, Sequence[int]] | None = None,
               core: TensorDictModuleBase | None = None, core_dim: int = 0) -> ProbabilisticActor:
    """A TanhNormal actor reading ``obs_key`` (flat), writing ``action_key`` and its log-prob, with
    the distribution parameters under ``(namespace, "loc")`` / ``(namespace, "scale")``.

    ``bounds`` (optional) is a module writing per-sample ``(namespace, "low")`` / ``(namespace, "high")``:
    the TanhNormal then spans those instead of the fixed ``[low, high]`` (a feed-forward plus a
    bounded learned residual, with the log-probability of the residual, as PPO needs).

    ``loc_bound`` > 0 keeps the pre-tanh mean within ±``loc_bound`` (``loc = b·tanh(loc/b)``, in the
    network). Unbounded, a mean driven far past the bounds with a small scale gives actions that
    float32 rounds onto the bound, whose log-probability then moves by tens of nats under a small
    weight change: PPO's ratio overflows (seen after 3.6 M frames of a specialist).

    ``latched`` (optional): entries fixed to N(0, 1) where an observation entry is > 0 (:class:`GaussianHeads`).
    ``blind`` (optional): heads that read no observation, one learned distribution each (:class:`GaussianHeads`).
    ``core`` (optional): a recurrent core (:func:`make_core`) run first; the trunk reads its
    ``(namespace, "memory")`` (``core_dim``) beside the normalized observation. Not with ``bounds``.

    ``torchrl_tanh_loc`` bounds it with TorchRL's ``TanhNormal(tanh_loc=True)`` instead, as checkpoints
    saved before 2026-11-25 did. That is not the same for per-sample bounds: TorchRL 0.14 then also
    adds the bounds' centre ``(low + high) / 2`` to the pre-tanh mean, so a residual tracker's zero
    correction became ``residual·tanh(feed-forward)`` on top of the feed-forward (tested in
    ``tests/modules/test_policy_modules.py``). Kept only so those checkpoints act as they were trained.

    Args:
        obs_key: the key of the flat observation it reads.
        obs_dim: the observation's size.
        head_sizes: the action entries of each output head (the action's size is their sum).
        low: the action's lower bound (fixed bounds; ignored for sampling when ``bounds`` is given,
            but still the action spec's).
        high: the action's upper bound, likewise.
        hidden: the trunk's hidden widths (:class:`GaussianHeads`).
        namespace: the key prefix of the distribution's entries.
        action_key: the key it writes the action to (default ``"action"``).
        init_scale: initial exploration scale, one for all heads or one per head (default 1.0).
        bounds: a module writing per-sample bounds (above), or None.
        loc_bound: bound of the pre-tanh mean (above; default 0: none).
        torchrl_tanh_loc: bound it TorchRL's way instead (above; default False).
        latched: ``(observation index, entries)`` fixed to N(0, 1) where that entry is > 0, a list of
            them, or None.
        blind: indices of the heads that read no observation (default none).
        blind_rate: the scale of their bias (:class:`GaussianHeads`; default 30).
        focus: ``{head index: observation indices}``, heads that read only those (:class:`GaussianHeads`).
        core: a recurrent core writing ``(namespace, "memory")`` (:func:`make_core`), or None (default).
        core_dim: the size of its memory.

    Returns:
        the ``ProbabilisticActor`` (TanhNormal, writing the log-prob; :class:`SamplingPolicy` samples it faster).
    """
    if core is not None and bounds is not None:
        raise ConfigError("make_actor: a recurrent core with per-sample bounds (a prior, held noise, a feed-forward) "
                          "is not supported")
    net = GaussianHeads(obs_dim, head_sizes, hidden, init_scale=init_scale,
                        loc_bound=0.0 if torchrl_tanh_loc else loc_bound, latched=latched, blind=blind,
                        blind_rate=blind_rate, focus=focus, extra_dim=core_dim if core is not None else 0)
    loc, scale = (namespace, "loc"), (namespace, "scale")
    if core is None:
        module = TensorDictModule(net, in_keys=[obs_key], out_keys=[loc, scale])
    else:
        module = TensorDictSequential(core, TensorDictModule(net, in_keys=[obs_key, (namespace, "memory")],
                                                             out_keys=[loc, scale]))
    dim = sum(head_sizes)
    dist_keys, dist_kwargs = {"loc": loc, "scale": scale}, {"low": low, "high": high}
    if bounds is not None:
        module = TensorDictSequential(module, bounds)
        dist_keys.update(low=(namespace, "low"), high=(namespace, "high"))
        dist_kwargs = {}
    if loc_bound > 0 and torchrl_tanh_loc:
        dist_kwargs.update(tanh_loc=True, upscale=float(loc_bound))
    actor = ProbabilisticActor(
        module, in_keys=dist_keys, out_keys=[action_key],
        spec=Bounded(low=low, high=high, shape=(dim,)), distribution_class=TanhNormal,
        distribution_kwargs=dist_kwargs, return_log_prob=True)
    # plain references (a tuple is not registered as a submodule: the state dict is unchanged)
    actor._sampling_parts = (net, bounds, obs_key, loc, scale, dist_keys, dist_kwargs)
    actor._core = core
    return actor


def stored_bounds_actor(actor: ProbabilisticActor) -> ProbabilisticActor:
    """``actor`` (from :func:`make_actor`) as a loss calls it on collected batches: with per-sample
    ``bounds``, the same network and TanhNormal reading the bounds the collecting policy wrote,
    ``(namespace, "low")`` / ``(namespace, "high")``, instead of computing them again; without, ``actor``.

    The bounds are a function of the observation alone, with no parameters, so a batch already holds
    them, exactly as the action was sampled between them. For a residual tracker with the object
    anchor, recomputing them costs its Jacobians on every minibatch: on the specialist benchmark's
    batches the update took 0.42 instead of 0.53 s per 4096 frames (medians over a 1 M-frame run),
    with the same losses to the last bit. The returned actor shares ``actor``'s parameters and has its
    state-dict keys (the bounds module holds no state), so a loss built on it saves and loads the same
    checkpoints as one built on ``actor``.

    >>> import torch
    >>> from tensordict import TensorDict
    >>> from tensordict.nn import TensorDictModule
    >>> half = TensorDictModule(lambda x: (x[..., :2] - 1, x[..., :2] + 1), in_keys=["obs"],
    ...                         out_keys=[("p", "low"), ("p", "high")])
    >>> actor = make_actor("obs", 4, [2], -1.0, 1.0, [8], namespace="p", bounds=half)
    >>> td = actor(TensorDict({"obs": torch.zeros(3, 4)}, batch_size=[3]))
    >>> sorted(stored_bounds_actor(actor).in_keys, key=str)
    [('p', 'high'), ('p', 'low'), 'obs']
    """
    _, bounds, _, _, _, dist_keys, kwargs = actor._sampling_parts
    if bounds is None:
        return actor
    module = actor.module[0].module[0]                      # the network's TensorDictModule, before the bounds
    (action_key,) = actor.module[-1].dist_sample_keys
    return ProbabilisticActor(TensorDictSequential(module), in_keys=dist_keys, out_keys=[action_key],
                              spec=actor.spec[action_key], distribution_class=TanhNormal,
                              distribution_kwargs=dict(kwargs), return_log_prob=True)


class SamplingPolicy(TensorDictModuleBase):
    """``actor`` (from :func:`make_actor`) as collectors call it: the same TanhNormal, sampled in one call.

    A collector calls its policy once per env step on every world. At B = 64 the ProbabilisticActor's
    generic path — a TensorDictModule call per piece, each output converted on write, the interaction
    type dispatched — costs about as much as its network (measured in ``benchmarks/train_throughput.py``).
    Under ``ExplorationType.RANDOM`` (what collectors set) this module runs the actor's own network
    and bounds modules on the tensors, builds the same :class:`~torchrl.modules.TanhNormal`, samples
    it and writes every key the actor writes; any other exploration type runs the actor itself. It
    holds the actor (its parameters), so a collector's weight updates reach both paths.

    Args:
        actor: an actor built by :func:`make_actor` without a recurrent core (another raises
            :class:`~adadex.errors.ConfigTypeError`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> actor = make_actor("obs", 4, [2], -1.0, 1.0, [8], namespace="p")
        >>> td = TensorDict({"obs": torch.zeros(3, 4)}, batch_size=[3])
        >>> with set_exploration_type(ExplorationType.RANDOM):
        ...     out = SamplingPolicy(actor)(td)
        >>> out["action"].shape, out["action_log_prob"].shape
        (torch.Size([3, 2]), torch.Size([3]))
    """

    def __init__(self, actor: ProbabilisticActor):
        super().__init__()
        parts = getattr(actor, "_sampling_parts", None)
        if parts is None:
            raise ConfigTypeError(f"SamplingPolicy needs an actor built by make_actor, got {type(actor).__name__}")
        if getattr(actor, "_core", None) is not None:
            raise ConfigTypeError("SamplingPolicy runs the actor's network alone; an actor with a recurrent core "
                                  "runs as it is")
        self.actor = actor
        self.in_keys, self.out_keys = list(actor.in_keys), list(actor.out_keys)
        sampler = actor.module[-1]                  # the ProbabilisticTensorDictModule: its output keys
        (self._action_key,), self._log_prob_key = sampler.dist_sample_keys, sampler.log_prob_key

    def forward(self, tensordict):
        if interaction_type() is not InteractionType.RANDOM:
            return self.actor(tensordict)
        net, bounds, obs_key, loc_key, scale_key, dist_keys, kwargs = self.actor._sampling_parts
        obs = tensordict.get(obs_key)
        loc, scale = net(obs)
        tensordict.set(loc_key, loc)
        tensordict.set(scale_key, scale)
        if bounds is not None:
            low, high = bounds.module(*(tensordict.get(k) for k in bounds.in_keys))
            tensordict.set(dist_keys["low"], low)
            tensordict.set(dist_keys["high"], high)
            kwargs = {**kwargs, "low": low, "high": high}
        dist = TanhNormal(loc, scale, **kwargs)
        action = dist.rsample()
        tensordict.set(self._action_key, action)
        tensordict.set(self._log_prob_key, dist.log_prob(action))
        return tensordict


def make_critic(obs_key, obs_dim: int, hidden: Sequence[int], *, value_key="state_value") -> ValueOperator:
    """A value network reading ``obs_key`` (flat) and writing ``value_key``.

    A :class:`Normalizer`, then an ELU MLP to one output.

    Args:
        obs_key: the key of the flat observation it reads.
        obs_dim: the observation's size.
        hidden: the MLP's hidden widths.
        value_key: the key it writes (default ``"state_value"``).
    """
    net = nn.Sequential(Normalizer(obs_dim), MLP(in_features=obs_dim, out_features=1, num_cells=list(hidden),
                                                 activation_class=nn.ELU))
    return ValueOperator(net, in_keys=[obs_key], out_keys=[value_key])


class ActorCritic(nn.Module):
    """An ``actor`` + ``critic`` pair with a ``config`` dict that rebuilds it: forward = the actor,
    :meth:`freeze`, and checkpoints (``save`` / ``load``, atomic, refusing another kind's file).

    A base class: a subclass sets ``actor``, ``critic``, ``config`` and its ``kind``.

    Args:
        *args: ``nn.Module``'s (none).
        **kwargs: ``nn.Module``'s (none).
    """

    kind = "actor_critic"
    config: dict

    def forward(self, tensordict):
        """The actor's forward pass (the module used as a policy)."""
        return self.actor(tensordict)

    def sampling_policy(self) -> SamplingPolicy:
        """The actor as collectors call it: :class:`SamplingPolicy` (same distribution, one call)."""
        return SamplingPolicy(self.actor)

    def zero_mean(self):
        """The actor's heads at zero (weights and biases), so its pre-tanh mean is 0 whatever it reads:
        a tracker's deterministic action is then its feed-forward (replay for a residual tracker), a
        modulator's its prior (no edit without one). Returns ``self``.

        >>> import torch
        >>> from tensordict import TensorDict
        >>> from adadex.modules.modulator import Modulator
        >>> mod = Modulator("T", hidden=(8,), inputs="observation").zero_mean()
        >>> float(mod.actor(TensorDict({"observation": torch.rand(2, 273)}, [2]))["modulator", "loc"].abs().max())
        0.0
        """
        with torch.no_grad():
            for head in self.actor._sampling_parts[0].heads:
                head.weight.zero_()
                head.bias.zero_()
        return self

    def freeze(self):
        """No gradients, eval mode (e.g. the tracker as the modulator's frozen generalist)."""
        self.requires_grad_(False)
        return self.eval()

    def save(self, path) -> Path:
        """Write config + weights to ``path`` atomically."""
        return atomic_write(path, lambda f: torch.save(
            {"kind": self.kind, "config": self.config, "state_dict": self.state_dict()}, f))

    @classmethod
    def load(cls, path, **changes):
        """The module saved at ``path``. ``changes``: constructor settings to take instead of the saved
        ones, for settings that hold no weights, e.g. ``Tracker.load(p, anchor_reach=0.10)``."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no {cls.kind} checkpoint there")
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # torch raises several types for a damaged file
            raise CheckpointError(f"{path}: not a readable {cls.kind} checkpoint ({e})") from e
        kind = blob.get("kind") if isinstance(blob, dict) else None
        if kind != cls.kind:
            raise CheckpointError(f"{path}: not a {cls.kind} checkpoint (kind={kind!r})")
        config = cls.upgrade_config(dict(blob["config"]))
        unknown = sorted(set(changes) - set(config))
        if unknown:
            raise ConfigError(f"{path}: a {cls.kind} has no settings {unknown}; it has {sorted(config)}")
        out = cls(**{**config, **changes})
        out.load_state_dict(blob["state_dict"])
        return out

    @classmethod
    def upgrade_config(cls, config: dict) -> dict:
        """A saved config as this version's constructor takes it (checkpoints of older versions)."""
        return config


def fit_normalizers(module: nn.Module, observations: torch.Tensor) -> None:
    """Fit every :class:`Normalizer` inside ``module`` (actor and critic) to sampled observations.

    Args:
        module: a module holding normalizers (e.g. an :class:`ActorCritic`).
        observations: (…, obs_dim) samples, at least 2 and finite.
    """
    for m in module.modules():
        if isinstance(m, Normalizer):
            m.fit(observations)


class ObservationMoments:
    """Running mean and variance of every observation seen so far, for the :class:`Normalizer` s of a
    module in training (the running input normalization of PPO for dexterous hands).

    Fitted on one batch, a normalizer describes only the states of that batch. PPO's first batch holds
    each episode's first ``frames_per_batch / worlds`` steps, with the object at rest: on a specialist
    benchmark the object's height got a scale of 2.3 mm there, so every lifted object read as 10 σ (the
    clip) and a fifth of the reference object's future positions was clipped over an evaluation
    (docs/training-log.md). Merged batch by batch (Chan et al.'s parallel update, in float64), the
    statistics cover the whole episode once the collection has reached its end. PPO uses them with
    ``ppo.obs_norm="running"``; it is not the default, because on that benchmark specialists trained so
    completed 0.8 and 1.8 points less than with the first batch's fit (two seeds).

    >>> m = ObservationMoments()
    >>> m.update(torch.tensor([[0.0], [2.0]])); m.update(torch.tensor([[4.0], [6.0]]))
    >>> m.count, m.mean.tolist(), m.std.tolist()
    (4, [3.0], [2.581988897471611])
    """

    def __init__(self):
        self.count, self.mean, self._m2 = 0, None, None

    def update(self, samples: torch.Tensor) -> None:
        """Merge ``samples`` (…, dim) into the statistics."""
        x = samples.reshape(-1, samples.shape[-1]).double()
        if not torch.isfinite(x).all():
            raise ArrayError("ObservationMoments.update: the observations hold non-finite values")
        n, mean = x.shape[0], x.mean(0)
        m2 = ((x - mean) ** 2).sum(0)
        if self.count == 0:
            self.count, self.mean, self._m2 = n, mean, m2
            return
        total = self.count + n
        delta = mean - self.mean
        self.mean = self.mean + delta * n / total
        self._m2 = self._m2 + m2 + delta ** 2 * self.count * n / total
        self.count = total

    @property
    def std(self) -> torch.Tensor:
        """Sample standard deviation (as :meth:`Normalizer.fit` computes it)."""
        return (self._m2 / max(self.count - 1, 1)).sqrt()

    def apply(self, module: nn.Module) -> None:
        """Give every :class:`Normalizer` inside ``module`` these statistics (its ``eps`` rule kept)."""
        if self.count < 2:
            raise ArrayError(f"ObservationMoments.apply needs ≥ 2 samples, got {self.count}")
        for m in module.modules():
            if isinstance(m, Normalizer):
                m.set_statistics(self.mean, self.std)

    def state_dict(self) -> dict:
        return {"count": self.count, "mean": self.mean, "m2": self._m2}

    def load_state_dict(self, state: dict) -> None:
        self.count, self.mean, self._m2 = int(state["count"]), state["mean"], state["m2"]
