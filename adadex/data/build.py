"""Build a reference dataset: instructions → synthesized human motion → retargeted robot reference
→ feasibility filter → splits → dataset folder. This is what ``adadex data build`` runs.

Presets (:data:`PRESETS`):

``tiny``   a few references on four objects (one held out) — for tests, seconds;
``small``  hundreds of references over all 80 objects — for CPU experiments;
``paper``  the paper's size: 505 base instructions × 10 paraphrases over 50 objects (45 seen + the 5
           held out) — for machines that can afford it.

Splits written with the dataset (``splits.json``), disjoint by construction:

``unseen_trajectory``  references on seen objects, 80 % train / 20 % test at random: the 20 % whose
                       name ranks first by a hash keyed with the seed, so which part a reference is in
                       does not depend on which other references the build accepted (a change that
                       drops or adds a few moves at most as many others across);
``unseen_object``      the same train part; test = every reference on a held-out object
                       (:func:`adadex.sim.objects.held_out_objects`), none of which is ever in a train part.

Every random choice derives from ``seed``; the same seed builds the same dataset.

Example::

    from adadex.data.build import build_dataset
    report = build_dataset("tiny", "data/tiny", seed=0)
    print(report.summary())
"""

from __future__ import annotations

import hashlib
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from adadex.data import feasibility
from adadex.data.object_contact import ObjectContact
from adadex.data.planned_grasp import PLANNER_VERSION, PlannedGraspError, plan_hold
from adadex.data.presets import PRESETS, Preset
from adadex.data.reference import Reference, is_dataset, save_dataset
from adadex.data.retarget import Retargeter
from adadex.data.synth import VERBS, HumanMotion, NoiseConfig, Synthesizer, make_instruction
from adadex.errors import ConfigError
from adadex.io import check_output
from adadex.progress import progress_bar
from adadex.sim.objects import held_out_objects


@dataclass
class BuildReport:
    """What a build produced and how long each stage took."""

    preset: str
    seed: int
    candidates: int = 0
    accepted: int = 0
    rejected: Counter = field(default_factory=Counter)
    rejections: list = field(default_factory=list)      # [{name, reason, frame, detail}]
    seconds: dict = field(default_factory=dict)          # stage → wall-clock seconds
    retargeted_frames: int = 0
    path: str | None = None

    def summary(self) -> str:
        rej = ", ".join(f"{k} {v}" for k, v in sorted(self.rejected.items())) or "none"
        secs = ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items())
        return (f"{self.preset}: {self.accepted} of {self.candidates} references accepted (rejected: {rej}); "
                f"{self.retargeted_frames} frames retargeted; {secs}")

    def as_dict(self) -> dict:
        d = asdict(self)
        d["rejected"] = dict(self.rejected)
        return d


def plan_instructions(preset: Preset, seed: int):
    """The preset's base instructions: verbs and objects assigned round-robin in a seeded order."""
    rng = np.random.default_rng([seed, 1])
    objects = list(rng.permutation(preset.objects))
    verbs = list(rng.permutation(VERBS))
    out = []
    for i in range(preset.base_instructions):
        obj = objects[i % len(objects)]
        verb = verbs[(i + i // len(objects)) % len(verbs)]
        out.append(make_instruction(str(verb), str(obj), seed=int(rng.integers(2 ** 31))))
    return out


def references_from_motions(motions: list[HumanMotion], group_ids: list[int], names: list[str],
                            retargeter: Retargeter, config: feasibility.FeasibilityConfig, report: BuildReport,
                            batch: int = 64, progress: bool = True, planned_grasp: bool = False):
    """Retarget motions in batches and keep the feasible references (rejections go to ``report``).
    With ``planned_grasp`` the hold is a pinch planned for this hand (:mod:`adadex.data.planned_grasp`)."""
    out = []
    frames = sum(len(m.keypoints) for m in motions)
    order = sorted(range(len(motions)), key=lambda i: len(motions[i].keypoints))
    batches = [order[s: s + batch] for s in range(0, len(order), batch)]
    lengths = [max(len(motions[i].keypoints) for i in idx) for idx in batches]
    bar = progress_bar(total=sum(len(b) * T for b, T in zip(batches, lengths)), desc="retarget", unit="frame",
               disable=not progress, leave=False)
    t0 = time.perf_counter()
    results = []
    for idx, T in zip(batches, lengths):
        kp = np.stack([np.pad(motions[i].keypoints, ((0, T - len(motions[i].keypoints)), (0, 0), (0, 0)),
                              mode="edge") for i in idx])
        obj = np.stack([np.pad(motions[i].object_pose, ((0, T - len(motions[i].object_pose)), (0, 0)), mode="edge")
                        for i in idx])
        res = retargeter.retarget(kp, lengths=[len(motions[i].keypoints) for i in idx], progress=bar.update,
                                  object_pose=obj, object_names=[motions[i].instruction.object_name for i in idx])
        results += [(i, res, j) for j, i in enumerate(idx)]
    bar.close()
    report.seconds["retarget"] = report.seconds.get("retarget", 0.0) + time.perf_counter() - t0
    report.retargeted_frames += frames

    t0 = time.perf_counter()
    for i, res, j in progress_bar(sorted(results, key=lambda r: r[0]), desc="check", disable=not progress, leave=False):
        m = motions[i]
        T = len(m.keypoints)
        q, meta = res.joint_pos[j, :T], dict(m.meta)
        if planned_grasp:
            try:
                meta["planned_grasp"] = {}
                q = plan_hold(q, m.object_pose, m.instruction.object_name, m.phases, fps=m.fps,
                              info=meta["planned_grasp"])
            except PlannedGraspError as e:
                report.rejected["no_planned_grasp"] += 1
                report.rejections.append({"name": names[i], "reason": "no_planned_grasp", "frame": None,
                                          "detail": str(e)})
                continue
        ref = Reference.from_joint_positions(
            q, m.object_pose, object_name=m.instruction.object_name,
            instruction=m.instruction.text, group_id=group_ids[i], fps=m.fps, human_keypoints=m.keypoints,
            retarget_residual=res.residual[j, :T], name=names[i],
            meta=dict(meta, retarget_scale=float(res.scale[j]),
                      retarget_tip_error_max=float(res.tip_error[j, :T].max()),
                      retarget_palm_error_max=float(res.palm_error[j, :T].max())))
        rej = feasibility.check(ref, retarget_palm_error=res.palm_error[j, :T],
                                retarget_tip_error=res.tip_error[j, :T], config=config)
        if rej is None:
            out.append(ref)
        else:
            report.rejected[rej.reason] += 1
            report.rejections.append(dict(name=names[i], **rej.as_dict()))
    report.seconds["check"] = report.seconds.get("check", 0.0) + time.perf_counter() - t0
    return out


def make_splits(refs: list[Reference], seed: int, test_fraction: float = 0.2) -> dict:
    """``unseen_trajectory`` and ``unseen_object`` splits (see the module docstring)."""
    held = set(held_out_objects())
    seen = [i for i, r in enumerate(refs) if r.object_name not in held]
    unseen = [i for i, r in enumerate(refs) if r.object_name in held]
    keys, count = [], Counter()
    for r in refs:                              # a name seen again is told apart by its occurrence
        keys.append(f"{r.name}#{count[r.name]}")
        count[r.name] += 1
    perm = sorted(seen, key=lambda i: hashlib.blake2b(f"{seed}:{keys[i]}".encode(), digest_size=8).digest())
    n_test = int(round(test_fraction * len(seen)))
    test, train = sorted(perm[:n_test]), sorted(perm[n_test:])
    return {"unseen_trajectory": {"train": train, "test": test},
            "unseen_object": {"train": train, "test": unseen}}


def dataset_at(path, *, preset: str | None, setting: str, seed: int = 0, planned_grasp: bool = False,
               progress: bool = True, log=print, hint: str = "") -> Path:
    """The reference dataset at ``path``, built there from ``preset`` when there is none: the one
    build-if-missing of every recipe (training, the pipeline, the sim-to-real loop).

    A folder that holds a dataset is used as it is (``log`` says so where its planned grasp was made by an
    earlier planner than today's, :data:`~adadex.data.planned_grasp.PLANNER_VERSION`: its references are
    not the ones a build makes now); a missing or empty one is built into (``log`` says so first); with
    ``preset`` None, or a folder that holds other files, nothing is built and a one-line
    ``FileNotFoundError`` names ``setting`` (the key the user set, e.g. ``"dataset"``), with ``hint`` (how
    to get one) after it.
    """
    from adadex.data.reference import ReferenceDataset, is_dataset

    path = Path(path)
    if is_dataset(path):
        info = ReferenceDataset(path).info
        if info.get("planned_grasp") and info.get("planner", 1) < PLANNER_VERSION:
            log(f"note: {path} was built by grasp planner {info.get('planner', 1)}, not today's {PLANNER_VERSION} "
                f"(docs/references.md); rebuild it into a new folder for today's references")
        return path
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise FileNotFoundError(f"{setting}={path}: not a reference dataset (no index.json), and not empty: "
                                f"nothing is built over it")
    if preset is None:
        raise FileNotFoundError(f"{setting}={path}: no reference dataset there" + (f" ({hint})" if hint else ""))
    log(f"building the {preset} reference dataset into {path}")
    build_dataset(preset, path, seed=seed, planned_grasp=planned_grasp, progress=progress)
    return path


def build_dataset(preset: str | Preset, out, *, seed: int = 0, noise: NoiseConfig = NoiseConfig(),
                  config: feasibility.FeasibilityConfig = feasibility.FeasibilityConfig(),
                  progress: bool = True, limit: int | None = None, force: bool = False,
                  contact: ObjectContact | None = None, planned_grasp: bool = False) -> BuildReport:
    """Build ``preset`` into the dataset folder ``out`` (written atomically); returns a :class:`BuildReport`.

    An existing dataset at ``out`` is replaced; anything else there is refused unless ``force``
    (see :func:`~adadex.data.reference.save_dataset`), checked before the build starts.

    ``limit`` caps the number of base instructions (for quick looks at a large preset). ``contact``:
    object-aware retargeting (:mod:`adadex.data.object_contact`); ``None`` (default) retargets
    keypoints only. ``planned_grasp``: the hand holds the object with a pinch planned for it
    (:mod:`adadex.data.planned_grasp`) instead of the retargeted human grasp.

    Args:
        preset: a preset name (a key of ``PRESETS``, e.g. ``"tiny"``) or a :class:`Preset`.
        out: the dataset folder to write.
        seed: seeds the instruction plan, the synthesis and the splits (default 0).
        noise: how imperfect the synthesized motion is (:class:`~adadex.data.synth.NoiseConfig`).
        config: the feasibility filter's settings (:class:`~adadex.data.feasibility.FeasibilityConfig`).
        progress: show progress bars (default True).
        limit: keep only the first ``limit`` base instructions (default None: all).
        force: replace whatever is at ``out`` (default False: only an existing dataset).
        contact: object-aware retargeting settings, or None (above).
        planned_grasp: hold the object with a planned pinch (above; default False).

    Returns:
        the :class:`BuildReport` (counts, rejections, timings and the path written).

    Raises:
        ConfigError: an unknown preset name.
        RuntimeError: no reference passed the feasibility filter.
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ConfigError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
        preset = PRESETS[preset]
    check_output(out, "dataset", force=force, recognize=is_dataset, option="force=True (--force on the command line)")
    report = BuildReport(preset.name, seed)
    t0 = time.perf_counter()
    synth = Synthesizer(noise)
    bases = plan_instructions(preset, seed)[:limit]
    motions, groups, names = [], [], []
    for g, base in enumerate(progress_bar(bases, desc="synthesize", disable=not progress, leave=False)):
        for instr in synth.paraphrases(base, preset.paraphrases, seed=seed * 100003 + g):
            name = f"g{g:04d}_p{instr.paraphrase}_{instr.verb}_{instr.object_name}"
            report.candidates += 1
            try:
                motions.append(synth.synthesize(instr, seed=seed * 1000003 + g * 10 + instr.paraphrase))
            except ValueError as e:
                report.rejected["no_grasp"] += 1
                report.rejections.append({"name": name, "reason": "no_grasp", "frame": None, "detail": str(e)})
                continue
            groups.append(g)
            names.append(name)
    report.seconds["synthesize"] = time.perf_counter() - t0
    refs = references_from_motions(motions, groups, names, Retargeter(contact=contact), config, report,
                                   progress=progress, planned_grasp=planned_grasp)
    report.accepted = len(refs)
    if not refs:
        raise RuntimeError(f"no reference of preset {preset.name!r} passed the feasibility filter: "
                           f"{dict(report.rejected)}")
    t0 = time.perf_counter()
    splits = make_splits(refs, seed)
    info = {"preset": preset.name, "seed": seed, "noise": asdict(noise), "feasibility": asdict(config),
            "object_contact": None if contact is None else asdict(contact), "planned_grasp": planned_grasp,
            **({"planner": PLANNER_VERSION} if planned_grasp else {}), "report": report.as_dict()}
    report.path = str(save_dataset(refs, Path(out), splits=splits, info=info, force=force))
    report.seconds["save"] = time.perf_counter() - t0
    return report
