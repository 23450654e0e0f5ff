"""From measurement to better tracking in one call: identify a hidden robot from recordings made on it,
train a modulator around the identified model, and measure tracking on the hidden robot (issue 42).

    python recipes/sim2real.py real=assets/gaps/weak_shoulder.json out=runs/s2r_shoulder preset=small

The hidden robot (``real``, a model patch file such as ``assets/gaps/*.json``) stands for a real one. It
is reached only through :class:`HiddenRobot`, which offers what a lab has: make recordings on it
(:meth:`HiddenRobot.record`: ``adadex sysid simulate`` of an excitation plan, with sensor noise) and run
evaluation rollouts on it (:meth:`HiddenRobot.evaluate`). Nothing else in this module reads its patch:
:func:`identify` gets the recording file alone.

Stages (:func:`run_sim2real`), each the library's own code:

1. **measure** — ``adadex sysid excite`` on every joint of the robot (a lab does not know where the
   model is wrong), then the recording on the hidden robot (:meth:`HiddenRobot.record`);
2. **identify** — ``adadex sysid diagnose`` → ``adadex sysid fit --accept`` → the identified patch, and
   the sysid error per stage (``adadex sysid compare --patch``): the workbench's commands, each run
   as a user runs it, in its own process (this module sits in the training layer, below the CLI);
3. **train** — modulators around the frozen tracker with :class:`~adadex.train.ppo.PPOTrainer` (the
   trainer behind ``recipes/train_modulator.py``): one under Table 3 on the nominal model
   (``modulator_table3``), one under :meth:`Randomization.from_patch` of the identified patch
   (``modulator_identified``: the fit's intervals around the fitted values, Table 3 elsewhere); with
   ``oracle`` also one around the hidden robot itself (the ceiling; it reads the hidden patch, and says so);
   and the tracker itself fine-tuned under the identified randomization with the same frames and learner
   (``finetuned_identified``, :func:`finetune_tracker`: what the budget buys without modulation);
4. **evaluate** — every row on the same references, repeats and env seed (so they pair episode by
   episode, :mod:`adadex.eval.paired`), under Table 3 randomization: the tracker on the nominal model
   (``tracker_nominal``), then on the hidden robot the tracker (``tracker_real``), the modulators, the
   fine-tuned tracker, and an
   untrained modulator as the control for Table 3's reshuffling (``modulator_untrained_real``).

``out/sim2real.json``: ``{"rows": {name: {"completion_pct", "completion_pct_ci95", "object_success_pct",
"object_success_pct_ci95", "T_o", …, "vs_tracker_real": {…}}}, "gap_points", "gap_points_ci95",
"recovered_fraction", "recovered_fraction_ci95", "diagnosis": {…}, "identified_patch", "stage_minutes",
…}`` with ``recovered_fraction`` = (modulator_identified_real − tracker_real) / (tracker_nominal −
tracker_real) in completion points (``None`` when the hidden robot loses nothing) and ``"verdict"``
(:func:`verdict`: nothing to recover, beyond the channels' reach, recovered, partly or not); intervals are
percentile bootstraps over references (all of a reference's repeats together). ``object_success_pct`` is
the object-centric success (object completion: frames with the object within 5 cm of the reference).
``out/sim2real.png``: each row's completion and T_o, and the sysid error falling.
"""

from __future__ import annotations

from collections.abc import Sequence

import dataclasses
import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adadex.errors import AdadexError, ConfigError, check_number
from adadex.sim.robot import JOINT_NAMES

#: the kind of output folder the recipe writes (its marker, :mod:`adadex.io`)
SIM2REAL_RUN = "sim2real run"

#: the rows in the order of the table
ROWS = ("tracker_nominal", "tracker_real", "modulator_untrained_real", "modulator_table3_real",
        "modulator_identified_real", "finetuned_identified_real", "modulator_oracle_real")
#: the trained rows whose share of the gap is reported (``recovered_fraction`` is the first's)
RECOVERING = ("modulator_identified_real", "modulator_table3_real", "finetuned_identified_real",
              "modulator_oracle_real")
#: paired completion differences reported beside the table: (row, row it is compared with, key)
CONTRASTS = (("modulator_identified_real", "modulator_table3_real", "identified_vs_table3_points"),
             ("modulator_identified_real", "finetuned_identified_real", "identified_vs_finetuned_points"))


#: the share of the gap the loop aims to take back (the sim-to-real issue's target): the verdict's bar
RECOVERY_TARGET = 0.5


class Sim2RealError(AdadexError, ValueError):
    """Bad input to the sim-to-real loop (a hidden robot that is not a patch, a bad preset …)."""


@dataclass(frozen=True)
class Sim2RealPreset:
    """Sizes of one run of the loop."""

    dataset: str | None             # a reference dataset folder; None: ``out/data``, built from ``build``
    build: str                      # the data build preset used when the dataset is missing
    build_seed: int
    planned_grasp: bool
    window: int                     # frames per episode (training and evaluation)
    eval_repeats: int               # episodes per test reference (each on its own Table 3 draw)
    worlds: int                     # worlds per batched env
    frames: int                     # PPO frames per trained modulator
    frames_per_batch: int
    minibatch_size: int
    epochs: int
    hidden: tuple[int, ...]         # the modulator's layers
    #: channel K, a feedback gain latched per episode: the edit that recovers a sagging arm (docs/sim2real.md)
    channels: str = "K"
    #: channels whose choice reads no observation — one learned value for every episode, the robot's
    #: (``ModulatorSettings.context_free``); those that ``channels`` lacks are left out
    context_free: tuple[str, ...] = ("K",)
    #: the modulator decides every this many control steps, its action held in between
    #: (``ModulatorSettings.decide_every``; 1: every step)
    decide_every: int = 1
    #: PPO's KL-adaptive rate (``PPOConfig.desired_kl``; for a modulator deciding every k steps, the KL at
    #: its decisions); 0: the constant rate the pipeline trains its modulators with
    desired_kl: float = 0.0
    gamma: float = 0.998            # PPO's discount and GAE λ: a choice latched at an episode's first step is
    lmbda: float = 1.0              # credited with the episode's return (docs/modulation.md, channel A)
    #: worlds that share a reference, a draw and the noise (``CollectorConfig.group_size``), and how PPO
    #: credits an action (``PPOConfig.advantage``: ``"group"`` compares the worlds of a group; measured in
    #: docs/sim2real.md, the default since 2026-12-06; ``group_size=1 advantage=gae``: as before)
    group_size: int = 4
    advantage: str = "group"
    reward: dict = field(default_factory=lambda: {"w_object_success": 3.0})
    #: :class:`~adadex.modules.channels.ModulationConfig` changes for every modulator, trained and
    #: evaluated alike (e.g. ``{"max_softening": 0.5}``: K may also soften a servo)
    modulation: dict = field(default_factory=dict)
    split: str = "unseen_trajectory"
    #: ``adadex sysid excite`` settings (every joint is excited)
    freqs: tuple[float, ...] = (0.5, 1.5, 3.0)
    amps: tuple[float, ...] = (0.5,)
    kinds: tuple[str, ...] = ("sine", "chirp", "multisine")
    poses: tuple[str, ...] = ("loaded",)
    duration: float = 3.0
    noise: float = 2e-4             # sensor noise of the recording, rad
    #: the effects ``adadex sysid diagnose`` screens (None: every effect it knows)
    candidates: tuple[str, ...] | None = None
    #: the physics of the training and evaluation envs (``SimConfig.backend``: ``"rollout"`` or ``"warp"``)
    #: and where the PPO updates run (``PPOConfig.device``); the workbench's replays stay on the CPU
    backend: str = "rollout"
    device: str = "cpu"


PRESETS = {
    # every stage at toy size (tests): a few hundred frames, 5 s episodes; no quality claim
    "tiny": Sim2RealPreset(dataset=None, build="tiny", build_seed=4, planned_grasp=False, window=60, eval_repeats=1,
                           worlds=8, frames=512, frames_per_batch=256, minibatch_size=128, epochs=1, hidden=(32, 32),
                           freqs=(1.0, 3.0), kinds=("sine", "chirp"), duration=2.0,
                           # a short list, for speed (small screens every effect the workbench knows)
                           candidates=("actuator_delay", "kp_scale", "torque_limit", "coulomb_friction")),
    # the modulation measurements' sizes (docs/modulation.md): data/small_pg, 25 s episodes, 4 draws per
    # test reference, 250 k frames per modulator in batches spanning whole episodes (64 × 300 steps)
    "small": Sim2RealPreset(dataset="data/small_pg", build="small", build_seed=0, planned_grasp=True, window=300,
                            eval_repeats=4, worlds=64, frames=250_000, frames_per_batch=19_200, minibatch_size=1024,
                            epochs=4, hidden=(256, 256, 128)),
}


#: the fields of :class:`Sim2RealPreset` (each a key of ``recipes/sim2real.py``)
PRESET_FIELDS = tuple(f.name for f in dataclasses.fields(Sim2RealPreset))


def _context_free(p: Sim2RealPreset) -> tuple[str, ...]:
    """The preset's context-free channels among those it trains."""
    from adadex.modules.channels import ModulationLayout

    return tuple(c for c in p.context_free if c in ModulationLayout(p.channels).channels)


def preset(name: str, **changes) -> Sim2RealPreset:
    """The preset ``name`` with ``changes`` (fields whose value is not None; ``reward`` and ``modulation``
    change the preset's settings they name), checked before any work: a bad value is one
    :class:`ConfigError` naming the key."""
    from adadex.envs.reward import RewardConfig
    from adadex.envs.tracking import TrackingConfig
    from adadex.modules.channels import ModulationConfig, ModulationLayout, parse_channels
    from adadex.train.config import SimConfig

    if name not in PRESETS:
        raise ConfigError(f"preset={name}: no such preset; known: {', '.join(PRESETS)}")
    unknown = sorted(set(changes) - set(PRESET_FIELDS))
    if unknown:
        raise ConfigError(f"{unknown[0]}: not a Sim2RealPreset field (known: {', '.join(PRESET_FIELDS)})")
    changes = {k: v for k, v in changes.items() if v is not None}
    for group in ("reward", "modulation"):
        if group in changes:
            changes[group] = {**getattr(PRESETS[name], group), **dict(changes[group])}
    p = dataclasses.replace(PRESETS[name], **changes)
    for key in ("eval_repeats", "worlds", "frames", "frames_per_batch", "minibatch_size", "epochs", "decide_every"):
        check_number(key, getattr(p, key), low=1, integer=True)
    for key, check in (("window", lambda: TrackingConfig(window=p.window)),
                       ("reward", lambda: RewardConfig(**p.reward)),
                       ("modulation", lambda: ModulationConfig(**p.modulation)),
                       ("channels", lambda: ModulationLayout(p.channels)),
                       ("context_free", lambda: parse_channels(p.context_free))):
        try:
            check()
        except (ConfigError, ValueError, TypeError) as e:
            raise ConfigError(f"{key}={getattr(p, key)}: {e}") from None
    p = dataclasses.replace(p, context_free=parse_channels(p.context_free))
    # a bad backend or device is refused before any work, named as the recipe's keys
    for key in ("gamma", "lmbda"):
        check_number(key, getattr(p, key), high=1.0)
    check_number("desired_kl", p.desired_kl, low=0.0)
    from adadex.train.config import CollectorConfig, PPOConfig

    def grouped():
        CollectorConfig(worlds=p.worlds, group_size=p.group_size)
        if p.advantage == "group" and p.group_size < 2:
            raise ConfigError("advantage=group needs group_size ≥ 2 (worlds to compare)")

    for key, check in (("backend", lambda: SimConfig(backend=p.backend)), ("device", lambda: PPOConfig(device=p.device)),
                       ("group_size", grouped), ("advantage", lambda: PPOConfig(advantage=p.advantage))):
        try:
            check()
        except ConfigError as e:
            raise ConfigError(f"{key}={getattr(p, key)}: {e}") from None
    if p.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ConfigError(f"device={p.device}: torch sees no CUDA device here")
    return p


# ----------------------------------------------------------------------------------------------
# The hidden robot: what a lab can do with a real one

class HiddenRobot:
    """A robot the loop may only record on and run rollouts on (see the module docstring): ``path`` is
    its patch file, checked to be one when the robot is "connected" and otherwise never shown."""

    def __init__(self, path):
        from adadex.sim.patch import ModelPatch, PatchError

        self._path = Path(str(path))
        if self._path.is_dir():
            raise Sim2RealError(f"real={path}: a folder, not a model patch file (e.g. assets/gaps/weak_shoulder.json)")
        try:
            self._patch = ModelPatch.load(self._path)
        except PatchError as e:
            raise Sim2RealError(f"real={e}") from None
        except (OSError, UnicodeDecodeError) as e:
            raise Sim2RealError(f"real={path}: not a readable model patch ({type(e).__name__}: {e})") from None
        if not len(self._patch.active()):
            raise Sim2RealError(f"real={path}: the patch has no effect, so the 'real' robot is the model itself")

    def __repr__(self) -> str:            # a log line never shows the hidden effects
        return "HiddenRobot(…)"

    def record(self, plan, out, *, noise: float, seed: int) -> Path:
        """Run the excitation ``plan`` (a plan file of ``adadex sysid excite``) on the robot and write what
        its encoders measured (with ``noise`` rad of sensor noise) to ``out``: ``adadex sysid simulate``."""
        sysid(["simulate", str(plan), "--patch", str(self._path), "--noise", repr(float(noise)),    # quiet: its
               "--seed", str(seed), "--out", str(out)], quiet=True)                           # message counts the effects
        print(f"recorded {out} on the hidden robot (sensor noise {noise:g} rad, seed {seed})", flush=True)
        return Path(out)

    def evaluate(self, policy, dataset, references, **kwargs) -> dict:
        """:func:`adadex.eval.evaluate.evaluate` of ``policy`` on the robot (``kwargs``: its arguments)."""
        from adadex.eval.evaluate import evaluate

        return evaluate(policy, dataset, split=None, references=references, patch=self._patch, **kwargs)

    def oracle_randomization(self):
        """Table 3 around the hidden robot itself: for the oracle row only (the ceiling, not a result)."""
        from adadex.envs.randomization import Randomization

        return Randomization.from_patch(self._patch)


def sysid(argv: list[str], *, quiet: bool = False, progress: bool = True) -> None:
    """Run ``adadex sysid ARGV`` as a user runs it, in its own process (``python -m adadex.cli``): the
    workbench as it ships, its output on this terminal (``quiet``: not its standard output; ``progress``:
    its progress bars). A refusal or failure raises :class:`Sim2RealError` with the command's own line."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "adadex.cli", "sysid", *argv], stderr=subprocess.PIPE,
                            stdout=subprocess.DEVNULL if quiet else None)
    tail = b""
    while chunk := proc.stderr.read1(4096) if hasattr(proc.stderr, "read1") else proc.stderr.read(4096):
        tail = (tail + chunk)[-4000:]
        if progress:
            sys.stderr.buffer.write(chunk)
            sys.stderr.flush()
    if proc.wait() != 0:
        lines = [x for x in tail.decode("utf-8", "replace").replace("\r", "\n").splitlines() if x.strip()]
        raise Sim2RealError(f"adadex sysid {argv[0]} failed: {lines[-1] if lines else f'exit code {proc.returncode}'}")


# ----------------------------------------------------------------------------------------------
# Identification: from a recording alone

def excite(folder: Path, p: Sim2RealPreset) -> Path:
    """``adadex sysid excite`` on every joint: ``folder/plan.npz``."""
    plan = folder / "plan.npz"
    sysid(["excite", "--joints", ",".join(JOINT_NAMES), "--freqs", ",".join(map(str, p.freqs)),
           "--amps", ",".join(map(str, p.amps)), "--kinds", ",".join(p.kinds), "--poses", ",".join(p.poses),
           "--duration", str(p.duration), "--out", str(plan)])
    return plan


def identify(recording, folder, *, candidates=None, threads: int = 2, progress: bool = True) -> dict:
    """diagnose → fit → patch on ``recording`` (a recording file) with the workbench's commands, into
    ``folder`` (``diagnosis/``, ``patch.json``, ``compare/``: the sysid error, baseline → each identified
    effect added). Reads nothing but the recording. Returns ``{"patch": ModelPatch, "diagnosis": the
    diagnosis.json fields, "stages": compare.json's stages}``."""
    from adadex.sim.patch import ModelPatch

    folder = Path(folder)
    rec, threads = str(recording), ["--threads", str(threads)]
    sysid(["diagnose", rec, "--out", str(folder / "diagnosis"), *threads,
           *(["--candidates", ",".join(candidates)] if candidates else [])], progress=progress)
    sysid(["fit", rec, "--accept", str(folder / "diagnosis"), "--out", str(folder / "patch.json"), *threads],
          progress=progress)
    sysid(["compare", rec, "--patch", str(folder / "patch.json"), "--out", str(folder / "compare"), *threads],
          progress=progress)
    compared = json.loads((folder / "compare" / "compare.json").read_text(encoding="utf-8"))
    nominal = compared["nominal"]
    stages = compared.get("stages") or {"stages": ["baseline (nominal model)"], "heldout": {"overall_rms_rad": [
        nominal["overall_rms_rad"]]}}
    return {"patch": ModelPatch.load(folder / "patch.json"),
            "diagnosis": json.loads((folder / "diagnosis" / "diagnosis.json").read_text(encoding="utf-8")),
            "stages": stages}


# ----------------------------------------------------------------------------------------------
# Training

def _trainer_class():
    from adadex.train.ppo import PPOTrainer

    class AroundModel(PPOTrainer):
        """:class:`PPOTrainer` whose collector envs draw from a given :class:`Randomization` (a patch
        and per-joint ranges, which a :class:`TrainConfig` cannot carry)."""

        def __init__(self, cfg, randomization, **kwargs):
            self.randomization = randomization
            super().__init__(cfg, **kwargs)

        def env_factory(self, seed: int):
            return dataclasses.replace(super().env_factory(seed), randomize=self.randomization)

    return AroundModel


def _ppo_config(p: Sim2RealPreset):
    """The learner of every trained row: the same frames and settings for modulators and the fine-tune."""
    from adadex.train.config import PPOConfig

    return PPOConfig(total_frames=p.frames, frames_per_batch=p.frames_per_batch, minibatch_size=p.minibatch_size,
                     epochs=p.epochs, desired_kl=p.desired_kl, update_threads=1,    # 0 as the pipeline trains modulators
                     gamma=p.gamma, lmbda=p.lmbda, device=p.device, advantage=p.advantage)


def fingerprint(module) -> str:
    """SHA-256 of a module's settings and weights: which tracker a stage was trained around or from
    (a checkpoint file's bytes are not stable across saves of the same weights)."""
    import hashlib

    h = hashlib.sha256(json.dumps(getattr(module, "config", None), sort_keys=True, default=str).encode())
    for k, v in sorted(module.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _train(folder, *, dataset, p: Sim2RealPreset, randomization, seed: int, name: str, inputs: dict,
           progress: bool, modulator=None, policy=None) -> str:
    """One PPO run in ``folder`` (a modulator with ``modulator`` settings, or ``policy`` trained as it is)
    with envs drawing from ``randomization``; returns its checkpoint. A finished run in ``folder`` with
    the same ``inputs`` (plus the shared settings) is kept, a killed one continues, other inputs start over."""
    from adadex.envs.tracking import TrackingConfig
    from adadex.io import atomic_write_text
    from adadex.train.config import CollectorConfig, SimConfig, TrainConfig

    folder = Path(folder)
    ppo = _ppo_config(p)
    inputs = {**inputs, "randomization": randomization.as_dict(), "window": p.window, "seed": seed,
              "reward": dict(p.reward), "hidden": list(p.hidden),
              "ppo": {k: getattr(ppo, k) for k in ("total_frames", "frames_per_batch", "minibatch_size", "epochs",
                                                   "gamma", "lmbda")},
              **({"advantage": p.advantage, "group_size": p.group_size}
                 if (p.advantage, p.group_size) != ("gae", 1) else {}),
              **({"desired_kl": p.desired_kl} if p.desired_kl else {}),
              **({"sim_backend": p.backend} if p.backend != SimConfig().backend else {})}
    stamp = folder.with_name(f"{folder.name}.inputs.json")      # beside the run: the trainer guards its folder
    same = stamp.is_file() and json.loads(stamp.read_text(encoding="utf-8")) == json.loads(json.dumps(inputs))
    if folder.exists() and not same:
        shutil.rmtree(folder)               # inside the recipe's own output: an earlier stage of other inputs
    tc = TrainConfig(dataset=str(dataset), out=str(folder), seed=seed, resume=(folder / "checkpoint.pt").is_file(),
                     split=(p.split, "train"), ppo=ppo, collector=CollectorConfig(worlds=p.worlds, group_size=p.group_size),
                     modulator=modulator, reward=dict(p.reward), eval_max_references=0, wandb=False,
                     sim=SimConfig(backend=p.backend), progress=progress)
    folder.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(stamp, json.dumps(inputs))
    trainer = _trainer_class()(tc, randomization, env_config=TrackingConfig(window=p.window), run_name=name,
                               policy=policy)
    return str(trainer.train()["policy"])


def train_modulator(folder, *, dataset, tracker: str, p: Sim2RealPreset, randomization, seed: int,
                    name: str, progress: bool = True) -> str:
    """A modulator (``p.channels``) around the frozen ``tracker`` (a checkpoint), trained in ``folder`` on
    ``dataset``'s training references with envs drawing from ``randomization``; returns its checkpoint.
    A finished run in ``folder`` with the same inputs (the tracker's weights among them) is kept (a
    killed one continues); other inputs start over."""
    from adadex.modules.tracker import Tracker
    from adadex.train.config import ModulatorSettings

    m = ModulatorSettings(tracker=str(tracker), channels=p.channels, hidden=p.hidden, context_free=_context_free(p),
                          modulation=dict(p.modulation), decide_every=p.decide_every)
    return _train(folder, dataset=dataset, p=p, randomization=randomization, seed=seed, name=name,
                  progress=progress, modulator=m,
                  inputs={"channels": p.channels, "tracker": fingerprint(Tracker.load(tracker)),
                          **({"context_free": list(_context_free(p))} if _context_free(p) else {}),
                          **({"modulation": dict(p.modulation)} if p.modulation else {}),
                          **({"decide_every": p.decide_every} if p.decide_every != 1 else {})})


def finetune_tracker(folder, *, dataset, tracker: str, p: Sim2RealPreset, randomization, seed: int,
                     name: str, progress: bool = True) -> str:
    """The tracker itself trained further — no modulator — with the same frames, learner and envs as a
    modulator (the ``finetuned_identified_real`` row: what the same budget buys without modulation).
    ``tracker``: a checkpoint, trained on from its weights and observation statistics as they are; or
    ``"replay"``: a residual tracker of the preset's layers whose correction starts at exactly zero
    (kinematic replay, as the frozen ``Tracker.replay()``), with the exploration the pipeline's trackers
    start from (:class:`~adadex.train.config.PolicyConfig`, no anchor). Returns its checkpoint."""
    from adadex.envs.tracking import TrackingConfig
    from adadex.modules.tracker import Tracker
    from adadex.train.config import PolicyConfig

    if tracker == "replay":
        import torch

        torch.manual_seed(seed)                     # its untrained critic and layers: the same for a seed
        policy = PolicyConfig(hidden=p.hidden, anchor=0.0).tracker(
            max_action=TrackingConfig(window=p.window).max_action).zero_mean()
    else:
        policy = Tracker.load(tracker)
    return _train(folder, dataset=dataset, p=p, randomization=randomization, seed=seed, name=name,
                  progress=progress, policy=policy, inputs={"finetune": fingerprint(policy)})


# ----------------------------------------------------------------------------------------------
# Statistics

def _aligned(rows: dict[str, dict], fields=("completion", "object_completion", "T_o")) -> dict:
    """Per-episode values of every row over the episodes all of them tracked (same reference and
    repeat, at least one frame each): ``{"reference": array, field: {row: array}}`` (percent, cm)."""
    from adadex.eval.paired import episode_keys

    keys = None
    index = {}
    for name, ep in rows.items():
        idx = {k: i for i, k in enumerate(episode_keys(ep)) if ep["frames"][i] > 0}
        index[name] = idx
        keys = set(idx) if keys is None else keys & set(idx)
    order = [k for k in episode_keys(next(iter(rows.values()))) if k in keys]
    scale = {"completion": 100.0, "object_completion": 100.0, "T_o": 100.0}
    out = {"reference": np.array([k[0] for k in order])}
    for f in fields:
        out[f] = {name: np.array([float(rows[name][f][index[name][k]]) * scale[f] for k in order]) for name in rows}
    return out


def ratio_bootstrap(numerator, denominator, reference_ids, seed_ids=None, *, resamples: int = 2000,
                    seed: int = 0) -> dict:
    """mean(numerator) / mean(denominator) over paired episodes, with a percentile bootstrap interval
    resampling references (each with all its episodes) within each seed (``seed_ids``: the strata,
    ``None``: one), as :func:`adadex.eval.paired.bootstrap_mean` resamples them; over seeds the ratio is
    that of the seeds' mean numerator and mean denominator. Resamples whose denominator is ≤ 0 count as
    −∞ (no gap to recover: the ratio is not defined there), so such resamples pull the lower end down
    instead of being dropped."""
    num, den = np.asarray(numerator, float), np.asarray(denominator, float)
    refs = np.asarray(reference_ids)
    seeds = np.zeros(len(num), dtype=np.int64) if seed_ids is None else np.asarray(seed_ids)
    rng = np.random.default_rng(seed)
    tn, td, est_n, est_d = np.zeros(int(resamples)), np.zeros(int(resamples)), 0.0, 0.0
    strata = np.unique(seeds)
    for k in strata:                                     # sorted: a fixed order of draws
        m = seeds == k
        _, inv = np.unique(refs[m], return_inverse=True)
        sn, sd, cnt = (np.bincount(inv, weights=num[m]), np.bincount(inv, weights=den[m]),
                       np.bincount(inv).astype(float))
        n = len(sn)
        if n == 0:
            continue
        draws = rng.multinomial(n, np.full(n, 1.0 / n), size=int(resamples)).astype(float)
        c = draws @ cnt
        tn += (draws @ sn) / c
        td += (draws @ sd) / c
        est_n, est_d = est_n + sn.sum() / cnt.sum(), est_d + sd.sum() / cnt.sum()
    if len(strata) == 0 or est_d <= 0:
        return {"estimate": None, "ci95": None}
    stats = np.where(td > 0, tn / np.where(td > 0, td, 1.0), -np.inf)
    lo, hi = np.quantile(stats, [0.025, 0.975])
    return {"estimate": float(est_n / est_d), "ci95": [float(lo), float(hi)], "seeds": int(len(strata))}


def row_statistics(evaluations: dict[str, dict], *, seed: int = 0) -> dict:
    """The table: each row's summary figures with bootstrap intervals, its paired difference to
    ``tracker_real``, the gap (``tracker_nominal − tracker_real``) and the recovered fraction."""
    from adadex.eval.paired import bootstrap_mean, paired_bootstrap

    al = _aligned({k: v["per_episode"] for k, v in evaluations.items()})
    refs = al["reference"]
    rows = {}
    for name, ev in evaluations.items():
        s = ev["summary"]
        row = {"completion_pct": s["completion_pct"], "object_success_pct": s["object_completion_pct"],
               "T_o": s["T_o"], "carried_pct": s.get("carried_pct"), "success_mean_error_pct": s["success_mean_error_pct"],
               "episodes": s["trajectories"]}
        row["completion_pct_ci95"] = bootstrap_mean(al["completion"][name], refs, seed=seed)["ci95"]
        row["object_success_pct_ci95"] = bootstrap_mean(al["object_completion"][name], refs, seed=seed)["ci95"]
        row["T_o_ci95"] = bootstrap_mean(al["T_o"][name], refs, seed=seed)["ci95"]
        if name != "tracker_real" and "tracker_real" in evaluations:
            row["vs_tracker_real"] = {
                f"{metric}_points": {k: d[k] for k in ("estimate", "ci95")}
                for metric, field_ in (("completion", "completion"), ("object_success", "object_completion"))
                for d in [paired_bootstrap(al[field_][name], al[field_]["tracker_real"], refs, seed=seed)]}
        rows[name] = row
    out = {"rows": rows, "paired_episodes": int(len(refs)), "references": int(len(np.unique(refs)))}
    if {"tracker_nominal", "tracker_real"} <= set(evaluations):
        c = al["completion"]
        gap = paired_bootstrap(c["tracker_nominal"], c["tracker_real"], refs, seed=seed)
        out["gap_points"], out["gap_points_ci95"] = gap["estimate"], gap["ci95"]
        o = al["object_completion"]
        ogap = paired_bootstrap(o["tracker_nominal"], o["tracker_real"], refs, seed=seed)
        out["object_gap_points"], out["object_gap_points_ci95"] = ogap["estimate"], ogap["ci95"]
        for name in RECOVERING:
            if name not in evaluations:
                continue
            r = ratio_bootstrap(c[name] - c["tracker_real"], c["tracker_nominal"] - c["tracker_real"], refs, seed=seed)
            key = "recovered_fraction" if name == "modulator_identified_real" else f"recovered_fraction_{name}"
            out[key], out[f"{key}_ci95"] = r["estimate"], r["ci95"]
        for a, b, key in CONTRASTS:
            if {a, b} <= set(evaluations):
                d = paired_bootstrap(c[a], c[b], refs, seed=seed)
                out[key] = {"estimate": d["estimate"], "ci95": d["ci95"]}
    out["verdict"] = verdict(out)
    return out


def format_fraction(x: float, ci=None, digits: int = 2) -> str:
    """A share of the gap with its interval, ``0.67 [0.50, 0.91]``; never ``-0.00``."""
    f = lambda v: f"{round(v, digits) + 0.0:.{digits}f}"        # noqa: E731 - + 0.0 turns -0.0 into 0.0
    return f(x) + (f" [{f(ci[0])}, {f(ci[1])}]" if ci else "")


def verdict(result: dict) -> dict:
    """What the table says about the hidden robot, in one word and one line: ``{"kind", "text"}``.

    ``kind`` is ``"no_gap"`` (the gap's interval reaches 0: nothing to recover), ``"beyond_reach"`` (the
    oracle row — a modulator trained on the hidden robot itself — takes back less than
    :data:`RECOVERY_TARGET` of the gap even at its interval's upper end: no identification can help this
    channel; a servo at its torque limit is the typical case), ``"recovered"`` (the identified modulator
    takes back at least :data:`RECOVERY_TARGET`, its interval's lower end above 0), ``"partly_recovered"``
    (lower end above 0, estimate below the target) or ``"not_recovered"``. ``result`` is
    :func:`row_statistics`' or :func:`pool_seeds`' output.

    >>> verdict({"gap_points": 9.0, "gap_points_ci95": [6.0, 12.0], "recovered_fraction": 0.7,
    ...          "recovered_fraction_ci95": [0.5, 0.9]})["kind"]
    'recovered'
    """
    gap, gap_ci = result.get("gap_points"), result.get("gap_points_ci95")
    if gap is None:
        return {"kind": "not_recovered", "text": "no gap measured (the tracker_nominal or tracker_real row is missing)"}
    if gap_ci is None or gap_ci[0] <= 0:
        return {"kind": "no_gap", "text": f"the hidden robot costs the tracker no completion these episodes resolve "
                                          f"(gap {gap:+.1f} {_ci(gap_ci)}): nothing to recover"}
    rf, ci = result.get("recovered_fraction"), result.get("recovered_fraction_ci95")
    oracle, oracle_ci = (result.get("recovered_fraction_modulator_oracle_real"),
                         result.get("recovered_fraction_modulator_oracle_real_ci95"))
    oracle_text = "" if oracle is None else format_fraction(oracle, oracle_ci)
    if oracle_ci is not None and oracle_ci[1] < RECOVERY_TARGET:
        return {"kind": "beyond_reach",
                "text": f"a modulator trained on the hidden robot itself takes back {oracle_text} of the "
                        f"{gap:.1f}-point gap: it lies beyond what these channels, trained this way, take back even on "
                        f"the robot itself (a servo at its torque limit, a load it cannot hold), so no better "
                        f"identification recovers it"}
    if rf is None or ci is None:
        return {"kind": "not_recovered", "text": f"the {gap:.1f}-point gap's recovered fraction is not defined"}
    digits = 3 if rf < RECOVERY_TARGET <= round(rf, 2) else 2          # 0.497 is not shown as the target
    share = f"the identified modulator takes back {format_fraction(rf, ci, digits)} of the {gap:.1f}-point gap"
    if ci[0] > 0 and rf >= RECOVERY_TARGET:
        return {"kind": "recovered", "text": share}
    if ci[0] > 0:
        return {"kind": "partly_recovered", "text": f"{share}, short of {RECOVERY_TARGET:.2f}"}
    tail = ("" if oracle is None or oracle_ci is None or oracle_ci[0] <= 0 else
            f"; trained on the hidden robot itself it takes back {oracle_text}: the channel can, the identified "
            f"model or the training falls short")
    return {"kind": "not_recovered", "text": share + tail}


def pool_seeds(results: Sequence[dict], *, seed: int = 0) -> dict:
    """Several runs of the loop on one hidden robot (``sim2real.json`` results, one per training seed)
    as one: every row's completion and object completion, the gap and the recovered fractions, the
    mean over seeds with intervals that resample references within each seed
    (:func:`adadex.eval.paired.bootstrap_mean`'s strata, :func:`ratio_bootstrap`). Each run's rows are
    paired on its own draws; runs of other hidden robots, or with rows missing, are refused."""
    from adadex.eval.paired import bootstrap_mean, paired_bootstrap

    results = list(results)
    if len(results) < 2:
        raise Sim2RealError(f"pool_seeds needs the results of at least 2 runs, got {len(results)}")
    reals = {str(r.get("real")) for r in results}
    if len(reals) != 1:
        raise Sim2RealError(f"pool_seeds: the runs are of different hidden robots: {sorted(reals)}")
    seeds = [r.get("seed") for r in results]
    if len(set(seeds)) != len(seeds):
        raise Sim2RealError(f"pool_seeds: two runs share a seed ({seeds}); pool runs of different seeds")
    names = [n for n in results[0]["per_episode"] if all(n in r["per_episode"] for r in results)]
    if not {"tracker_nominal", "tracker_real"} <= set(names):
        raise Sim2RealError("pool_seeds: every run needs the tracker_nominal and tracker_real rows")
    parts = [_aligned({n: r["per_episode"][n] for n in names}) for r in results]
    refs = np.concatenate([a["reference"] for a in parts])
    seed_ids = np.concatenate([np.full(len(a["reference"]), i) for i, a in enumerate(parts)])
    col = {f: {n: np.concatenate([a[f][n] for a in parts]) for n in names} for f in ("completion", "object_completion")}
    rows = {}
    for n in names:
        row = {}
        for metric, f in (("completion_pct", "completion"), ("object_success_pct", "object_completion")):
            b = bootstrap_mean(col[f][n], refs, seed_ids, seed=seed)
            row[metric], row[f"{metric}_ci95"] = b["estimate"], b["ci95"]
            if n != "tracker_real":
                d = paired_bootstrap(col[f][n], col[f]["tracker_real"], refs, seed_ids, seed=seed)
                row[f"vs_tracker_real_{metric.replace('_pct', '')}_points"] = {"estimate": d["estimate"],
                                                                               "ci95": d["ci95"]}
        rows[n] = row
    c = col["completion"]
    gap = paired_bootstrap(c["tracker_nominal"], c["tracker_real"], refs, seed_ids, seed=seed)
    out = {"real": results[0].get("real"), "seeds": seeds, "runs": len(results), "rows": rows,
           "paired_episodes": int(len(refs)), "gap_points": gap["estimate"], "gap_points_ci95": gap["ci95"],
           "per_seed_recovered_fraction": [r.get("recovered_fraction") for r in results]}
    for n in RECOVERING:
        if n in names:
            r = ratio_bootstrap(c[n] - c["tracker_real"], c["tracker_nominal"] - c["tracker_real"], refs, seed_ids,
                                seed=seed)
            key = "recovered_fraction" if n == "modulator_identified_real" else f"recovered_fraction_{n}"
            out[key], out[f"{key}_ci95"] = r["estimate"], r["ci95"]
    for a, b, key in CONTRASTS:
        if {a, b} <= set(names):
            d = paired_bootstrap(c[a], c[b], refs, seed_ids, seed=seed)
            out[key] = {"estimate": d["estimate"], "ci95": d["ci95"]}
    out["verdict"] = verdict(out)
    return out


def _ci(ci) -> str:
    return "" if not ci else f"[{ci[0]:+.1f}, {ci[1]:+.1f}]"


def format_table(result: dict) -> str:
    """The printed table: one line per row, then the gap and what was recovered."""
    lines = [f"{'row':28s} {'completion %':>22s} {'vs tracker_real':>22s} {'object %':>8s} {'vs tracker_real':>22s} "
             f"{'T_o cm':>7s}"]
    for name in ROWS:
        r = result["rows"].get(name)
        if r is None:
            continue
        v = r.get("vs_tracker_real")
        cmp_c = "" if v is None else f"{v['completion_points']['estimate']:+.1f} {_ci(v['completion_points']['ci95'])}"
        cmp_o = "" if v is None else (f"{v['object_success_points']['estimate']:+.1f} "
                                      f"{_ci(v['object_success_points']['ci95'])}")
        ci = r["completion_pct_ci95"]
        lines.append(f"{name:28s} {r['completion_pct']:6.1f} [{ci[0]:5.1f}, {ci[1]:5.1f}] {cmp_c:>22s} "
                     f"{r['object_success_pct']:8.1f} {cmp_o:>22s} {r['T_o']:7.2f}")
    if "gap_points" in result:
        lines.append(f"gap (tracker_nominal − tracker_real): {result['gap_points']:+.1f} completion points "
                     f"{_ci(result['gap_points_ci95'])}; object {result['object_gap_points']:+.1f} "
                     f"{_ci(result['object_gap_points_ci95'])}")
    for name in RECOVERING:
        key = "recovered_fraction" if name == RECOVERING[0] else f"recovered_fraction_{name}"
        if key in result:
            rf, ci = result[key], result.get(f"{key}_ci95")
            lines.append(f"recovered by {name}: " + (
                "not defined (the hidden robot loses no completion)" if rf is None else format_fraction(rf, ci)))
    if "verdict" in result:
        lines.append(f"verdict: {result['verdict']['kind']} — {result['verdict']['text']}")
    return "\n".join(lines)


def plot(result: dict, path) -> Path:
    """Each row's completion (with its interval) and T_o, and the sysid error falling (held-out RMS)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from adadex.io import atomic_write

    names = [n for n in ROWS if n in result["rows"]]
    rows = [result["rows"][n] for n in names]
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    y = np.arange(len(names))
    comp = np.array([r["completion_pct"] for r in rows])
    ci = np.array([r["completion_pct_ci95"] for r in rows]).T
    axes[0].barh(y, comp, xerr=[comp - ci[0], ci[1] - comp], color="tab:blue")
    axes[0].set_yticks(y, names, fontsize=8)
    axes[0].invert_yaxis()
    axes[0].set_xlabel("completion (%), 95 % interval")
    axes[1].barh(y, [r["T_o"] for r in rows], color="tab:orange")
    axes[1].set_yticks(y, [""] * len(names))
    axes[1].invert_yaxis()
    axes[1].set_xlabel("T_o (cm)")
    st = result["sysid"]["stages"]
    rms = np.degrees(st["heldout"]["overall_rms_rad"])
    axes[2].plot(range(len(rms)), rms, "o-")
    axes[2].set_xticks(range(len(rms)), ["nominal"] + [s.split(" on ")[0].lstrip("+ ") for s in st["stages"][1:]],
                       fontsize=7, rotation=20)
    axes[2].set_yscale("log")
    axes[2].set_ylabel("held-out joint RMS error (°)")
    axes[2].set_title("sysid: the error falling", fontsize=9)
    fig.suptitle(f"sim-to-real on {result['real']}", fontsize=10)
    fig.tight_layout()
    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)


def plot_robots(pooled: dict[str, dict], path) -> Path:
    """Several hidden robots side by side: for each (``{name: pool_seeds(…) result}``), every row's
    completion with its interval, and above the group the identified modulator's share of the gap (or the
    oracle's, where it is the only trained row) and the verdict. What the README's figure shows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from adadex.io import atomic_write

    shown = [n for n in ROWS if n != "modulator_untrained_real" and any(n in r["rows"] for r in pooled.values())]
    colors = {"tracker_nominal": "0.55", "tracker_real": "tab:red", "modulator_table3_real": "tab:orange",
              "modulator_identified_real": "tab:blue", "finetuned_identified_real": "tab:purple",
              "modulator_oracle_real": "tab:green"}
    fig, ax = plt.subplots(figsize=(max(6.0, 2.1 * len(pooled)), 4.8))
    width = 0.8 / len(shown)
    for i, (robot, res) in enumerate(pooled.items()):
        for j, name in enumerate(shown):
            row = res["rows"].get(name)
            if row is None:
                continue
            c, (lo, hi) = row["completion_pct"], row["completion_pct_ci95"]
            ax.bar(i - 0.4 + (j + 0.5) * width, c, width, yerr=[[c - lo], [hi - c]], color=colors[name],
                   label=name if i == 0 or name not in ax.get_legend_handles_labels()[1] else None, capsize=2)
        key = next((k for k in ("recovered_fraction", "recovered_fraction_modulator_oracle_real")
                    if res.get(k) is not None), None)
        note = res.get("verdict", verdict(res))["kind"].replace("_", " ")
        if key is not None:
            who = "identified" if key == "recovered_fraction" else "oracle"
            note = f"{who}: {format_fraction(res[key], res.get(f'{key}_ci95'))}\n{note}"
        ax.text(i, 101, note, ha="center", va="bottom", fontsize=7)
    ax.set_xticks(range(len(pooled)), list(pooled), fontsize=8)
    ax.set_ylim(0, 118)
    ax.set_ylabel("completion (%), 95 % interval")
    ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.1))
    ax.set_title("the share of the gap taken back, on each hidden robot", fontsize=9)
    fig.tight_layout()
    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)


# ----------------------------------------------------------------------------------------------
# The loop

def check_out(out, *, force: bool = False, ignore=()) -> Path:
    """The output guard: ``out`` absent, empty, an earlier sim2real output (its marker), or ``force``."""
    from adadex.io import check_output_dir

    return check_output_dir(Path(out), SIM2REAL_RUN, force=force, option="force=true", ignore=ignore)


def _dataset(p: Sim2RealPreset, dataset, out: Path) -> Path:
    from adadex.data.build import dataset_at

    return dataset_at(dataset or p.dataset or out / "data", preset=p.build, setting="dataset", seed=p.build_seed,
                      planned_grasp=p.planned_grasp, log=lambda m: print(m, flush=True))


def run_sim2real(real, out, *, tracker: str = "replay", preset_name: str = "small", seed: int = 0,
                 dataset=None, oracle: bool = False, force: bool = False, progress: bool = True,
                 threads: int = 2, ignore=(), **changes) -> dict:
    """The loop (module docstring); ``changes``: :class:`Sim2RealPreset` fields (None: the preset's);
    ``ignore``: names in ``out`` that are not in the way (what Hydra wrote there). Returns the result
    written to ``out/sim2real.json``."""
    import torch

    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import TrackingConfig, episode_references
    from adadex.data.reference import ReferenceDataset
    from adadex.io import atomic_write_text, json_default, mark_output_dir
    from adadex.modules.channels import ModulationConfig
    from adadex.modules.modulator import Modulator
    from adadex.modules.tracker import Tracker
    from adadex.transforms.policy import make_policy

    p = preset(preset_name, **changes)
    robot = HiddenRobot(real)                         # a bad real= is refused before any work
    if tracker != "replay" and not Path(str(tracker)).is_file():
        raise FileNotFoundError(f"tracker={tracker}: no such checkpoint file")
    loaded = Tracker.replay() if tracker == "replay" else _load_tracker(tracker)
    out = check_out(out, force=force, ignore=ignore)
    mark_output_dir(out, SIM2REAL_RUN)
    minutes: dict[str, float] = {}
    t_all = time.perf_counter()

    def stage(name: str, t0: float) -> None:
        minutes[name] = round((time.perf_counter() - t0) / 60, 2)

    t0 = time.perf_counter()
    data = _dataset(p, dataset, out)
    ds = ReferenceDataset(data)
    refs = episode_references(ds, (p.split, "test"), p.window)
    if not refs:
        raise ConfigError(f"{data}: no {p.split}/test reference has a {p.window}-frame episode window")
    stage("dataset", t0)
    tracker_path = out / "tracker.pt"
    if tracker == "replay":
        loaded.save(tracker_path)
    else:
        shutil.copyfile(tracker, tracker_path)
    loaded = loaded.freeze()

    # 1. measure, on the hidden robot
    t0 = time.perf_counter()
    lab = out / "sysid"
    lab.mkdir(exist_ok=True)
    print(f"\n[1/4] measure: adadex sysid excite on all {len(JOINT_NAMES)} joints, recorded on the hidden robot "
          f"(sensor noise {p.noise:g} rad)", flush=True)
    plan = excite(lab, p)
    recording = robot.record(plan, lab / "recording.npz", noise=p.noise, seed=seed)
    stage("measure", t0)

    # 2. identify, from the recording alone
    t0 = time.perf_counter()
    print("\n[2/4] identify: adadex sysid diagnose → fit --accept → patch", flush=True)
    ident = identify(recording, lab, candidates=p.candidates, threads=threads, progress=progress)
    patch = ident["patch"]
    print(f"identified: {patch.describe()}", flush=True)
    stage("identify", t0)

    # 3. train
    around = {"modulator_table3": Randomization(),
              "modulator_identified": Randomization.from_patch(patch) if len(patch.active()) else Randomization()}
    if oracle:
        around["modulator_oracle"] = robot.oracle_randomization()
    modulators = {}
    for name, randomization in around.items():
        t0 = time.perf_counter()
        print(f"\n[3/4] train {name} ({p.channels}, {p.frames} frames)", flush=True)
        modulators[name] = train_modulator(out / "train" / name, dataset=data, tracker=str(tracker_path), p=p,
                                           randomization=randomization, seed=seed, name=name, progress=progress)
        stage(f"train_{name}", t0)
    t0 = time.perf_counter()
    print(f"\n[3/4] train finetuned_identified (the tracker itself, {p.frames} frames)", flush=True)
    finetuned = finetune_tracker(out / "train" / "finetuned_identified", dataset=data,
                                 tracker="replay" if tracker == "replay" else str(tracker_path), p=p,
                                 randomization=around["modulator_identified"], seed=seed,
                                 name="finetuned_identified", progress=progress)
    stage("train_finetuned_identified", t0)

    # 4. evaluate: every row on the same episodes and draws
    episodes = refs * p.eval_repeats
    kw = dict(max_worlds=64, config=TrackingConfig(window=p.window),
              randomize=Randomization(), seed=20_000 + seed, progress=progress, nthread=threads, backend=p.backend)
    from adadex.eval.evaluate import evaluate

    torch.manual_seed(seed)
    untrained = Modulator(p.channels, hidden=p.hidden)
    edits = ModulationConfig(**p.modulation)
    policies = {"tracker_real": make_policy(loaded, None, channels="none"),
                "modulator_untrained_real": make_policy(loaded, untrained, config=edits),
                **{f"{k}_real": make_policy(loaded, Modulator.load(v), config=edits) for k, v in modulators.items()},
                "finetuned_identified_real": make_policy(Tracker.load(finetuned).freeze(), None, channels="none")}
    evaluations = {}
    t0 = time.perf_counter()
    print(f"\n[4/4] evaluate: {len(refs)} test references × {p.eval_repeats} draws, Table 3", flush=True)
    nominal = make_policy(loaded, None, channels="none")
    evaluations["tracker_nominal"] = _keep(evaluate(nominal, ds, split=None, references=episodes,
                                                    env_transform=nominal.primer, **kw))
    for name, policy in policies.items():
        evaluations[name] = _keep(robot.evaluate(policy, ds, episodes, env_transform=policy.primer, **kw))
        print(f"  {name}: completion {evaluations[name]['summary']['completion_pct']:.1f} %", flush=True)
    stage("evaluate", t0)
    minutes["total"] = round((time.perf_counter() - t_all) / 60, 2)

    choices = {k: Modulator.load(v).context_free_actions() for k, v in modulators.items()}
    for k, v in choices.items():
        if v:
            print(f"  {k} learned (context-free, the action in [-1, 1]): "
                  + ", ".join(f"{e} {[round(x, 3) for x in a]}" for e, a in v.items()), flush=True)
    stats = row_statistics(evaluations, seed=seed)
    d = ident["diagnosis"]
    result = {"real": str(real), "preset": preset_name, "seed": seed, "tracker": str(tracker), "dataset": str(data),
              "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(p).items()},
              "episodes": len(episodes), "condition": f"{p.split} test, Table 3 randomization",
              **stats,
              "diagnosis": {k: d.get(k) for k in ("verdict", "selected", "explained_fraction", "findings",
                                                   "wall_time_s")},
              "identified_patch": patch.to_dict(), "sysid": {"stages": ident["stages"]},
              # what each context-free choice learned (K: the arm's and the hand's gains are
              # max_gain · clip(a, −max_softening / max_gain, 1))
              "context_free_actions": choices,
              "stage_minutes": minutes,
              "per_episode": {k: v["per_episode"] for k, v in evaluations.items()}}
    atomic_write_text(out / "sim2real.json", json.dumps(result, indent=1, default=json_default))
    plot(result, out / "sim2real.png")
    return result


def _load_tracker(path):
    from adadex.errors import CheckpointError
    from adadex.modules.tracker import Tracker

    try:
        return Tracker.load(path)
    except (CheckpointError, ValueError) as e:
        raise ConfigError(f"tracker={path}: {str(e).split(' (')[0]}") from None


def _keep(res: dict) -> dict:
    return {"summary": res["summary"], "per_episode": res["per_episode"], "wall_s": res["wall_s"]}


