"""Once-per-episode choices fitted from paired rollouts: the simulator's counterfactuals instead of PPO's samples.

Channels A, L and K choose once per episode, at its first step (A: whether to reach for a displaced
object; L: a servo lead; K: servo gains). PPO learns such a choice from one sampled action per
episode, against a spread of returns across episodes far larger than what the choice changes: around
kinematic replay, PPO's channel A learned *that* reaching pays but not *when* — not with a head that
reads only the object's offset, not with 1 M frames (docs/modulation.md). A simulator can do what a
lab cannot: run the *same* episode — reference, Table 3 draw and noise — once per candidate choice
(an *arm*) and compare the returns. This fits the modulator's heads to those comparisons: one step of
classification-based policy iteration (Lagoudakis & Parr, ICML 2003) over the arms, around the
frozen tracker.

The fit maximizes the return of the choice itself: the deterministic action ``a`` (``tanh`` of each
head's mean, in [−1, 1]) picks arm ``k`` with the soft nearest-arm probability
``p_k ∝ exp(−|a − arm_k|² / τ)``, ``τ`` = ``temperature`` × the smallest squared distance between two
arms, and the loss is minus the expected advantage ``Σ_k p_k (R_k − mean R)`` over the episodes (a
cost-sensitive classification; full batch, AdamW). Where an arm is better on average for episodes
alike, the action runs to it and saturates there. (A weighted least-squares fit of the action to each
episode's best arm, tried first, landed between the arms — with arms −1, 0, 1 on the middle one,
where few episodes' best arm was.) The references are split into a fitting part and a held-out part;
the step with the best held-out loss is kept, and the report says what the fitted choice scores on
the held-out episodes (each scored by the arm nearest its action) against each arm alone and against
choosing with hindsight.

Every channel of the modulator must be latched (A, L, K with their ``*_latched`` switches on, in the
modulator and in the :class:`~adadex.modules.channels.ModulationConfig`): a channel that acts every
step has no per-episode counterfactual; train it with PPO. The critic is not trained; a fitted
modulator can be fine-tuned by PPO as any other (``PPOTrainer(…, policy=modulator)``).

Example (a tiny run; ``data/small_pg`` as the benchmarks use)::

    from adadex.modules.modulator import Modulator
    from adadex.modules.tracker import Tracker
    from adadex.train.paired_choice import PairedChoiceConfig, fit_paired_choice
    mod = Modulator("A", focus={"A": ["start_offset"]})
    report = fit_paired_choice(mod, Tracker.replay(), "data/small_pg", references=[0, 1, 2],
                               settings=PairedChoiceConfig(arms=(-1.0, 1.0), repeats=2), seed=0)
    mod.save("runs/a_paired/policy.pt")
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from adadex.errors import ConfigError, check_number

#: per-episode fields the report compares (the fraction of an episode's frames), besides the return
FIELDS = ("completion", "object_completion", "carried")


@dataclass(frozen=True)
class PairedChoiceConfig:
    """How :func:`fit_paired_choice` fits.

    Args:
        arms: the candidate actions tried on every episode, each a number (every entry of the
            modulator's action) or one value per entry; in [−1, 1]. For channel A with the clip map,
            ``-1`` is no reach and ``1`` full reach; ``0`` half.
        repeats: Table 3 draws per training reference.
        steps: AdamW steps (full batch).
        lr: AdamW's learning rate.
        weight_decay: AdamW's weight decay.
        holdout: the fraction of the references held out to pick the step (0: keep the last step).
        temperature: the soft choice's ``τ`` as a fraction of the arms' smallest squared distance
            (default 0.5: for arms −1 and 1, ``p_1 = sigmoid(2a)``).
    """

    arms: tuple = (-1.0, 1.0)
    repeats: int = 4
    steps: int = 2000
    lr: float = 3e-3
    weight_decay: float = 1e-3
    holdout: float = 0.25
    temperature: float = 0.5

    def __post_init__(self):
        if len(self.arms) < 2:
            raise ConfigError(f"PairedChoiceConfig.arms: at least two arms to compare, got {list(self.arms)}")
        for k, arm in enumerate(self.arms):
            values = [arm] if isinstance(arm, (int, float)) else arm
            if isinstance(values, str) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                  and -1.0 <= v <= 1.0 for v in values):
                raise ConfigError(f"PairedChoiceConfig.arms[{k}]: {arm!r} is not a number or numbers in [-1, 1]")
        check_number("PairedChoiceConfig.repeats", self.repeats, integer=True, strict_low=True)
        check_number("PairedChoiceConfig.steps", self.steps, integer=True, strict_low=True)
        check_number("PairedChoiceConfig.lr", self.lr, strict_low=True)
        check_number("PairedChoiceConfig.weight_decay", self.weight_decay)
        check_number("PairedChoiceConfig.holdout", self.holdout, high=0.9)
        check_number("PairedChoiceConfig.temperature", self.temperature, strict_low=True)


def arm_actions(arms: Sequence, dim: int) -> torch.Tensor:
    """``arms`` (numbers or ``dim``-long sequences) → a (K, dim) tensor, checked to lie in [−1, 1]."""
    rows = []
    for k, arm in enumerate(arms):
        values = [float(arm)] * dim if isinstance(arm, (int, float)) else [float(v) for v in arm]
        if len(values) != dim:
            raise ConfigError(f"PairedChoiceConfig.arms[{k}]: {len(values)} values for a {dim}-entry action")
        if not all(-1.0 <= v <= 1.0 for v in values):
            raise ConfigError(f"PairedChoiceConfig.arms[{k}]: {values} is outside [-1, 1]")
        rows.append(values)
    return torch.tensor(rows, dtype=torch.float32)


def check_latched(layout, modulation, modulator_config: dict | None = None) -> None:
    """Refuse channels (a :class:`~adadex.modules.channels.ModulationLayout`) that are not all chosen once
    per episode by the env's :class:`ModulationConfig` (and by the modulator's ``config``, when given)."""
    for record in layout.records:
        if not record.latch:
            raise ConfigError(f"paired choice: channel {record.name} of {layout.name} acts every step, "
                              "not once per episode (only A, L and K latch); train it with PPO")
        if not getattr(modulation, record.latch) or (modulator_config is not None
                                                     and not modulator_config.get(record.latch, False)):
            raise ConfigError(f"paired choice: channel {record.name} needs {record.latch}=True in the modulator "
                              "and the ModulationConfig")


def forced(modulator, action: torch.Tensor):
    """A copy of ``modulator`` whose deterministic action is ``action`` (D,) whatever it reads: each
    head's weights zero, its mean's bias the value whose ``tanh`` (through ``loc_bound``) is the action."""
    out = copy.deepcopy(modulator)
    net = out.heads
    start = 0
    with torch.no_grad():
        for i, (head, n) in enumerate(zip(net.heads, net.head_sizes)):
            loc = torch.atanh(action[start:start + n].clamp(-0.9999, 0.9999))
            if net.loc_bound > 0:
                loc = net.loc_bound * torch.atanh((loc / net.loc_bound).clamp(-0.9999, 0.9999))
            if i in net.blind:
                loc = loc / net.blind_rate
            head.weight.zero_()
            head.bias[:n] = loc
            start += n
    return out


def _step0_inputs(policy, modulator, ds, episodes, *, seed, config, randomize, max_worlds, nthread, **env_kwargs):
    """What the modulator reads at each episode's first step ((N, obs_dim)); the same for every arm."""
    from adadex.envs.chunked import chunked_rollouts

    parts = [part.rollout[modulator.obs_key][:, 0] for part in chunked_rollouts(
        policy, ds, episodes, max_worlds=max_worlds, seed=seed, config=config, env_transform=policy.primer,
        steps=1, progress=False, randomize=randomize, nthread=nthread, **env_kwargs)]
    return torch.cat(parts)


def _scores(pick: np.ndarray, per_arm: dict, rows: np.ndarray) -> dict:
    """Mean return and % fields over ``rows`` when episode ``i`` gets arm ``pick[i]``."""
    out = {"return": float(per_arm["return"][rows, pick[rows]].mean())}
    out.update({f: float(100 * per_arm[f][rows, pick[rows]].mean()) for f in FIELDS})
    return out


def fit_paired_choice(modulator, tracker, dataset, references: Sequence[int],
                      settings: PairedChoiceConfig = PairedChoiceConfig(), *, seed: int = 0, config=None,
                      modulation=None, randomize=None, max_worlds: int = 64, progress: bool = True,
                      nthread: int = 2, **env_kwargs) -> dict:
    """Fit ``modulator``'s latched heads (in place) to paired rollouts of each arm (see the module docstring).

    Args:
        modulator: a :class:`~adadex.modules.modulator.Modulator` whose channels all latch (A, L, K).
        tracker: the frozen tracker it modulates (e.g. ``Tracker.replay()`` or a generalist).
        dataset: a :class:`~adadex.data.reference.ReferenceDataset` or its folder.
        references: the training references (dataset indices), each run ``settings.repeats`` times.
        settings: the arms and the fit (:class:`PairedChoiceConfig`).
        seed: the env seed of the rollouts (every arm meets the same draws) and of the held-out split.
        config: the episode settings (default ``TrackingConfig()``), reward included.
        modulation: the env's :class:`~adadex.modules.channels.ModulationConfig` (default ``ModulationConfig()``).
        randomize: the randomization (default Table 3, ``Randomization()``).
        max_worlds: worlds stepped together.
        progress: a progress bar per arm.
        nthread: physics threads.
        env_kwargs: further :class:`~adadex.envs.tracking.TrackingEnv` arguments (``backend``, ``patch`` …).

    Returns:
        a report: ``episodes``, ``frames`` (steps simulated), ``arms``, ``step`` (the one kept),
        ``fit_loss``/``holdout_loss``, ``arm_return`` (each arm's mean return over all episodes) and
        ``holdout``: the fitted choice (each held-out episode scored by the arm nearest its action),
        each arm alone and the best arm with hindsight, as mean return and % completion, object
        completion and carried; ``per_episode``: each episode's ``reference``, whether it was
        ``held_out``, the fitted ``action`` at its first step and the arm it is nearest (``pick``), and
        per arm its ``return`` and :data:`FIELDS` ((episodes, arms) lists); ``wall_s``.
    """
    from adadex.data.reference import ReferenceDataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import TrackingConfig
    from adadex.eval.evaluate import evaluate
    from adadex.modules.channels import ModulationConfig
    from adadex.transforms.policy import make_policy

    t0 = time.perf_counter()
    config = TrackingConfig() if config is None else config
    modulation = ModulationConfig() if modulation is None else modulation
    randomize = Randomization() if randomize is None else randomize
    check_latched(modulator.layout, modulation, modulator.config)
    arms = arm_actions(settings.arms, modulator.layout.dim)
    gaps = torch.cdist(arms, arms) ** 2
    if not (gaps > 0).any():
        raise ConfigError(f"PairedChoiceConfig.arms: {arms.tolist()} holds no two different arms")
    tau = settings.temperature * gaps[gaps > 0].min()
    references = [int(r) for r in references]
    if not references:
        raise ConfigError("paired choice: no training references")
    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    episodes = references * settings.repeats
    per_arm: dict[str, list] = {}
    for k, arm in enumerate(arms):
        policy = make_policy(tracker, forced(modulator, arm), config=modulation)
        res = evaluate(policy, ds, split=None, references=episodes, max_worlds=max_worlds,
                       env_transform=policy.primer, config=config, randomize=randomize, seed=seed,
                       progress=progress, nthread=nthread, **env_kwargs)
        for f in ("return", *FIELDS):
            per_arm.setdefault(f, []).append(np.asarray(res["per_episode"][f], float))
    per_arm = {f: np.stack(v, 1) for f, v in per_arm.items()}           # (N, K)
    x = _step0_inputs(make_policy(tracker, modulator, config=modulation), modulator, ds, episodes, seed=seed,
                      config=config, randomize=randomize, max_worlds=max_worlds, nthread=nthread, **env_kwargs)

    gen = torch.Generator().manual_seed(seed)
    unique = sorted(set(references))
    held = set(np.asarray(unique)[torch.randperm(len(unique), generator=gen).numpy()[
        :min(int(round(settings.holdout * len(unique))), len(unique) - 1)]].tolist())
    is_held = np.array([r in held for r in episodes])
    fit_rows = np.flatnonzero(~is_held)
    held_rows = np.flatnonzero(is_held)
    returns = torch.as_tensor(per_arm["return"], dtype=torch.float32)
    best = returns.argmax(1)
    advantage = returns - returns.mean(1, keepdim=True)
    spread = advantage.abs().mean().clamp_min(1e-9)            # the loss in units of a typical arm's advantage
    net = modulator.heads
    if not net.norm.fitted:
        net.norm.fit(x[fit_rows])
    params = [p for p in net.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=settings.lr, weight_decay=settings.weight_decay)

    def loss_on(rows) -> torch.Tensor:
        loc, _ = net(x[rows])
        p = torch.softmax(-torch.cdist(torch.tanh(loc), arms) ** 2 / tau, -1)
        return -(p * advantage[rows]).sum(-1).mean() / spread

    best_state, best_loss, best_step = copy.deepcopy(net.state_dict()), float("inf"), 0
    for step in range(1, settings.steps + 1):
        opt.zero_grad()
        loss = loss_on(fit_rows)
        loss.backward()
        opt.step()
        if len(held_rows):
            with torch.no_grad():
                check = float(loss_on(held_rows))
            if check < best_loss:
                best_state, best_loss, best_step = copy.deepcopy(net.state_dict()), check, step
    if len(held_rows):
        net.load_state_dict(best_state)
    else:
        best_step = settings.steps
    with torch.no_grad():
        fitted = torch.tanh(net(x)[0])
        pick = torch.cdist(fitted, arms).argmin(1).numpy()
        fit_loss = float(loss_on(fit_rows))
    rows = held_rows if len(held_rows) else fit_rows
    report = {"episodes": len(episodes), "references": len(unique), "held_out_references": len(held),
              "frames": len(episodes) * len(arms) * (config.window - 1), "arms": arms.tolist(),
              "step": best_step, "fit_loss": fit_loss, "holdout_loss": best_loss if len(held_rows) else None,
              "arm_return": per_arm["return"].mean(0).tolist(),
              "holdout": {"episodes": int(len(rows)), "fitted": _scores(pick, per_arm, rows),
                          "arms": [_scores(np.full(len(episodes), k), per_arm, rows) for k in range(len(arms))],
                          "hindsight": _scores(best.numpy(), per_arm, rows),
                          "arm_fraction": np.bincount(pick[rows], minlength=len(arms)).tolist()},
              "per_episode": {"reference": episodes, "held_out": is_held.tolist(), "pick": pick.tolist(),
                              "action": fitted.tolist(),
                              **{f: per_arm[f].tolist() for f in ("return", *FIELDS)}},
              "wall_s": time.perf_counter() - t0}
    return report
