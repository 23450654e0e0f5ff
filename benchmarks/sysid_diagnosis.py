"""Full 22-joint diagnosis on data with hidden effects: accuracy, parameter errors, time.

Every one of the 22 joints gets a hidden effect (the 12 library effects dealt out over the joints
in a seeded order, at a clearly visible size); one recording excites all joints (per-joint sine
sweeps and chirps, loaded and unloaded poses, 2 s each at 60 Hz, sensor noise 0.2 mrad); the
workbench diagnoses it without seeing the truth. Reported: top-1 accuracy (the truth is the best
hypothesis for its joint, or an indistinguishable alternative of it), relative parameter error of
correct top-1 fits, held-out excess-error reduction, verdict, wall time and the time of each stage of
the diagnosis (localize, fit, relocalize, joint refit and scoring).
Target: the whole diagnosis under 5 minutes on 2 cores.

``--payloads``: a mass hung on a link with an MjSpec edit of the exported world (palm: at its flange, at
its own centre of mass and at its link's; index fingertip, forearm; 2 s pre-roll at rest, 0.2 mrad
noise, all 22 joints measured while 2-4 joints of the chain are excited; ``tests/sysid/hidden.py``),
diagnosed on the built-in model; ``--case NAME`` (repeatable) runs only those. Reported per case: the
selected effects, whether the one selected effect is ``payload_mass`` on the link that carries the mass,
the mass's relative error (target ≤ 5 %, explained, nothing else selected: ``ok``), the fitted offset
where the payload has one, and where the mass truly hangs in the payload's terms (``true_offset_m``
along the link's distal axis from the link's centre of mass, ``true_off_axis_m`` off that axis;
:func:`adadex.sim.effects.payload_point`), the explained fractions, the verdict and the wall time.

``--worst``: the worst case, one source felt on 15+ joints (:data:`WORST`): a torque-limited shoulder
(arm_j2 and arm_j3 at 0.3 of their effort, ``assets/gaps/weak_shoulder.json``: the shoulder cannot hold the
loaded pose, so every sequence moves the arm) and a shoulder limited on arm_j2 alone at 0.35 (it barely
holds); recorded as the sim2real recipe's ``small`` preset excites (every joint, sine at 0.5/1.5/3 Hz,
chirp and multisine, amplitude 0.5, loaded pose, 3 s each at 60 Hz; sensor noise 0.2 mrad), diagnosed
with every library effect. ``--case NAME`` (repeatable) runs only those. Reported per case: the failing
joints, the selected effects and their values against the truth, the verdict, wall and process-CPU time
of the whole diagnosis, the wall time of each of its stages (and their CPU time where the diagnosis reports
``stage_cpu_s``), and how many replays (and sequences replayed) each step of the diagnosis ran.

    python benchmarks/sysid_diagnosis.py [--seed 0] [--out FILE]
    python benchmarks/sysid_diagnosis.py --payloads [--case palm] [--out FILE]
    python benchmarks/sysid_diagnosis.py --worst [--case shoulder] [--out FILE]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from _data import check_result, write_result
from adadex.sim.effects import EFFECT_NAMES, get_effect
from adadex.sim.patch import ModelPatch
from adadex.sim.robot import JOINT_NAMES, joint_group
from adadex.sysid.diagnose import diagnose
from adadex.sysid.excite import design_excitation, simulate_recording

RESULTS = Path(__file__).resolve().parent / "results"

#: (case, body the mass hangs on, position in the body's frame, kg, excited joints, the robot joint whose
#: link carries the body). ``payload_mass`` puts its mass at the combined centre of mass of the link (link4;
#: if_ds; link6 and the palm together, 4.3 cm beyond the palm's frame origin). Positions: that point
#: (link4, if_ds: their own centre of mass; ``palm_link_com``); the palm's own centre of mass, 1.2 cm beyond
#: it (6.5 cm beyond link6's); the palm's frame origin (the flange, 1 cm from link6's centre of mass). Along
#: the link's distal axis (:func:`true_offset`): palm −4.33 cm (on the axis), palm_com +1.17 cm (0.05 mm off
#: it), palm_link_com 0, fingertip −0.005 cm, forearm −0.011 cm (0.47 mm off it).
_WRIST = ("arm_j2", "arm_j3", "arm_j5", "th_mcp")
PAYLOADS = (
    ("palm", "palm", (0.0, 0.0, 0.0), 0.6, _WRIST, "arm_j6"),
    ("palm_com", "palm", (0.0, -0.00247478, 0.05493321), 0.6, _WRIST, "arm_j6"),
    ("palm_link_com", "palm", (0.0, -0.00190976, 0.04324141), 0.6, _WRIST, "arm_j6"),
    ("fingertip", "if_ds", (0.0, 0.0, 0.0197), 0.05, ("if_mcp", "if_pip"), "if_dip"),
    ("forearm", "link4", (0.0, 0.026, -0.025), 1.0, ("arm_j2", "arm_j3", "arm_j4"), "arm_j4"),
)


def true_offset(body: str, pos, joint: str) -> tuple[float, float]:
    """Where a mass hung on ``body`` at ``pos`` sits as ``payload_mass`` on ``joint``'s link would put it:
    (offset along the link's distal axis from the link's centre of mass, distance off that axis), m."""
    import mujoco

    from adadex.sim.effects import ModelBase, link_bodies, payload_point, robot_ids

    m = ModelPatch().build_model()
    base = ModelBase.of(m)
    jnt = int(robot_ids(m, [JOINT_NAMES.index(joint)])[0][0])
    bodies = link_bodies(m, [jnt])[0]
    c = payload_point(m, base, jnt, bodies, 0.0)
    u = payload_point(m, base, jnt, bodies, 1.0) - c
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    root, b = m.jnt_bodyid[jnt], m.body(body).id
    p = d.xmat[root].reshape(3, 3).T @ (d.xpos[b] + d.xmat[b].reshape(3, 3) @ np.asarray(pos) - d.xpos[root])
    s = float((p - c) @ u)
    return s, float(np.linalg.norm(p - c - s * u))


def payload_cases(seed: int, threads: int, only=None) -> dict:
    """Diagnose each of :data:`PAYLOADS` (or those named in ``only``); see the module docstring."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.sysid import hidden

    rows = []
    for case, body, pos, mass, excited, joint in PAYLOADS:
        if only and case not in only:
            continue
        model = hidden.edited_model(hidden.hang_mass(body, mass, pos), f"payload_{case}")
        rec = hidden.recording(model, list(excited), seed=seed, nthread=threads)
        t0 = time.perf_counter()
        d = diagnose(rec, nthread=threads, progress=False)
        secs = time.perf_counter() - t0
        sel = [(h["effect"], h["joints"], h["params"]) for h in d.selected]
        one = len(sel) == 1 and sel[0][0] == "payload_mass" and sel[0][1] == [joint]
        rel = abs(sel[0][2]["mass"][0] - mass) / mass if one else None
        offset = sel[0][2]["offset"][0] if one and "offset" in sel[0][2] else None
        true, off_axis = true_offset(body, pos, joint)
        ok = one and rel <= 0.05 and d.verdict == "explained"
        rows.append({"case": case, "body": body, "mass": mass, "excited": list(excited), "link_joint": joint,
                     "failing": sorted(d.explained_fraction),
                     "selected": sel, "one_payload_on_its_link": one, "mass_rel_error": rel,
                     "offset_m": offset, "true_offset_m": true, "true_off_axis_m": off_axis,
                     "ci95": d.selected[0].get("ci95") if one else None,
                     "explained_min": min(d.explained_fraction.values()) if d.explained_fraction else None,
                     "verdict": d.verdict, "suggestions": [s["effect"] for s in d.suggestions],
                     "seconds": secs, "stage_seconds": d.stage_times_s, "ok": ok})
        where = (f", offset {'not fitted' if offset is None else f'{100 * offset:+.2f} cm'} "
                 f"(true {100 * true:+.2f} cm)")
        print(f"{case:<13} {mass:g} kg on {body}: {sel} {'OK' if ok else 'WRONG'} "
              f"(mass error {rel if rel is None else f'{100 * rel:.2f}%'}{where}), verdict {d.verdict}, "
              f"{secs:.0f} s", flush=True)
    return {"benchmark": "sysid_diagnosis", "mode": "payloads", "seed": seed, "cases": rows,
            "all_within_5pct": all(r["ok"] for r in rows)}

#: (case, {effect: (joints, value)}): one source felt on 15+ joints (module docstring, ``--worst``)
WORST = (
    ("shoulder", {"torque_limit": (("arm_j2", "arm_j3"), 0.3)}),
    ("shoulder_j2", {"torque_limit": (("arm_j2",), 0.35)}),
)


#: the diagnosis's modules (:mod:`adadex.sysid.diagnose` and the steps it calls): a replay is credited to them
DIAGNOSIS_FILES = tuple(f"adadex/sysid/{m}.py" for m in ("diagnose", "scoring", "source_first", "load_search",
                                                         "joint_selection"))


class _Counter:
    """Counts the replays (calls, and sequences replayed) of every :class:`~adadex.sysid.replay.Replayer` while
    installed, by the step of the diagnosis that asked (the outermost function of :data:`DIAGNOSIS_FILES`
    under ``diagnose``: ``_source_first``, ``_forward_selection``, ``_follows``, …) and the kind of replay."""

    def __init__(self):
        from adadex.sysid.replay import Replayer

        self.calls, self.seqs = {}, {}
        self._orig = {}
        for name in ("simulate", "simulate_windows", "simulate_imposed"):
            orig = getattr(Replayer, name)
            self._orig[name] = orig
            setattr(Replayer, name, self._wrap(name, orig))

    def _wrap(self, name, orig):
        import inspect

        def wrapped(rep, *args, **kwargs):
            frame = inspect.currentframe().f_back
            while frame is not None and not _in_diagnosis(frame):
                frame = frame.f_back
            # the outermost diagnosis function below diagnose() names the step
            site, f = "other", frame
            while f is not None and _in_diagnosis(f):
                if f.f_code.co_name != "diagnose":
                    site = f.f_code.co_name
                f = f.f_back
            seqs = kwargs.get("sequences")
            n = len(rep.rec.joint_pos) if seqs is None else len(np.atleast_1d(seqs))
            key = f"{site}.{name}"
            self.calls[key] = self.calls.get(key, 0) + 1
            self.seqs[key] = self.seqs.get(key, 0) + n
            return orig(rep, *args, **kwargs)
        return wrapped

    def close(self):
        from adadex.sysid.replay import Replayer

        for name, orig in self._orig.items():
            setattr(Replayer, name, orig)


def _in_diagnosis(frame) -> bool:
    return frame.f_code.co_filename.replace("\\", "/").endswith(DIAGNOSIS_FILES)


def worst_cases(seed: int, threads: int, only=None) -> dict:
    """Diagnose each of :data:`WORST` (or those named in ``only``); see the module docstring."""
    from adadex.train.sim2real import PRESETS

    small = PRESETS["small"]
    plan = design_excitation(JOINT_NAMES, freqs=small.freqs, amps=small.amps, kinds=small.kinds, poses=small.poses,
                             duration=small.duration)
    rows = []
    for case, effects in WORST:
        if only and case not in only:
            continue
        truth = ModelPatch()
        for effect, (joints, value) in effects.items():
            truth = truth.with_effect(effect, list(joints), value)
        rec = simulate_recording(plan, truth, noise=2e-4, seed=seed, nthread=threads)
        counter = _Counter()
        w0, c0 = time.perf_counter(), time.process_time()
        try:
            d = diagnose(rec, nthread=threads, progress=False)
        finally:
            counter.close()
        secs, cpu = time.perf_counter() - w0, time.process_time() - c0
        sel = [(h["effect"], h["joints"], h["params"]) for h in d.selected]
        found = {}
        for effect, (joints, value) in effects.items():
            h = next((h for h in d.selected if h["effect"] == effect), None)
            got = dict(zip(h["joints"], list(h["params"].values())[0])) if h else {}
            found[effect] = {j: {"truth": value, "fitted": got.get(j),
                                 "rel_error": None if got.get(j) is None else abs(got[j] - value) / value}
                             for j in joints}
        exact = sorted((e, tuple(sorted(j))) for e, (j, _) in effects.items())
        same = sorted((h["effect"], tuple(sorted(h["joints"]))) for h in d.selected) == exact
        within = all(v["rel_error"] is not None and v["rel_error"] <= 0.1 for f in found.values() for v in f.values())
        ok = same and within and d.verdict == "explained"
        rows.append({"case": case, "truth": {e: [list(j), v] for e, (j, v) in effects.items()},
                     "sequences": rec.num_sequences, "failing": sorted(d.explained_fraction),
                     "num_failing": len(d.explained_fraction), "selected": sel, "truth_vs_fitted": found,
                     "only_the_truth_selected": same, "within_10pct": within,
                     "explained_min": min(d.explained_fraction.values()) if d.explained_fraction else None,
                     "verdict": d.verdict, "suggestions": [s["effect"] for s in d.suggestions],
                     "seconds": secs, "cpu_seconds": cpu, "stage_seconds": d.stage_times_s,
                     "stage_cpu_seconds": d.to_dict().get("stage_cpu_s"),
                                          "replays": counter.calls, "sequences_replayed": counter.seqs, "ok": ok})
        print(f"{case}: {len(d.explained_fraction)} failing; selected {sel}; {'OK' if ok else 'WRONG'}; "
              f"verdict {d.verdict}; {secs:.0f} s wall, {cpu:.0f} s CPU; stages {d.stage_times_s}; "
              f"replays {counter.calls}", flush=True)
    return {"benchmark": "sysid_diagnosis", "mode": "worst", "seed": seed, "recording": "sim2real small preset",
            "cases": rows, "all_ok": all(r["ok"] for r in rows)}


#: Sizes that leave a clear mark; the library's nominal values otherwise.
VISIBLE = {("payload_mass", "finger"): 0.1, ("payload_mass", "thumb"): 0.1, ("payload_mass", "arm_shoulder"): 1.5,
           ("payload_mass", "arm_wrist"): 1.0, ("armature", "arm_wrist"): 0.08, ("coulomb_friction", "arm_wrist"): 1.5}


def truth_patch(seed: int) -> ModelPatch:
    rng = np.random.default_rng(seed)
    deck = list(EFFECT_NAMES) * 2
    rng.shuffle(deck)
    patch = ModelPatch()
    for joint, effect in zip(JOINT_NAMES, deck):
        eff = get_effect(effect)
        base = VISIBLE.get((effect, joint_group(joint)), float(eff.nominal_values([joint])[0, 0]))
        lo, hi = (float(b[0, 0]) for b in eff.bounds([joint]))
        value = float(np.clip(base * rng.uniform(0.8, 1.2), lo, hi)) if base != 0 else base
        patch = patch.with_effect(effect, [joint], value)
    return patch


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, default=RESULTS / "sysid_diagnosis.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    p.add_argument("--payloads", action="store_true", help="the hidden-payload cases instead (module docstring)")
    p.add_argument("--worst", action="store_true", help="the worst cases instead (module docstring)")
    p.add_argument("--case", action="append", choices=[c[0] for c in PAYLOADS] + [c[0] for c in WORST],
                   help="with --payloads or --worst: only this case (repeatable); default all")
    a = p.parse_args(argv)
    if a.payloads and a.out == p.get_default("out"):
        a.out = RESULTS / "sysid_payloads.json"
    if a.worst and a.out == p.get_default("out"):
        a.out = RESULTS / "sysid_worst.json"
    check_result(a.out, name="sysid_diagnosis", force=a.force)      # before any work: refuse a file not ours
    if a.worst:
        out = worst_cases(a.seed, a.threads, a.case)
        write_result(a.out, out, name="sysid_diagnosis", force=a.force, indent=2)
        return out
    if a.payloads:
        out = payload_cases(a.seed, a.threads, a.case)
        write_result(a.out, out, name="sysid_diagnosis", force=a.force, indent=2)
        return out

    truth = truth_patch(a.seed)
    plan = design_excitation(JOINT_NAMES, freqs=(0.5, 2.0), amps=(0.3, 1.0), kinds=("sine", "chirp"), duration=2.0)
    t0 = time.perf_counter()
    rec = simulate_recording(plan, truth, noise=2e-4, seed=a.seed, nthread=a.threads)
    t_sim = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    d = diagnose(rec, nthread=a.threads)
    t_diag, c_diag = time.perf_counter() - t0, time.process_time() - c0

    rows = []
    for e in truth.effects:
        joint, value = e.joints[0], float(e.values[0, 0])
        hyps = [h for h in d.hypotheses if h["joints"] == [joint]]
        top = hyps[0] if hyps else None
        correct = bool(top and (top["effect"] == e.effect or e.effect in top["alternatives"]))
        fitted = list(top["params"].values())[0][0] if top else None
        rel = abs(fitted - value) / abs(value) if (top and top["effect"] == e.effect and value) else None
        rows.append({"joint": joint, "truth_effect": e.effect, "truth_value": value,
                     "top1_effect": top["effect"] if top else None, "top1_alternatives": top["alternatives"] if top else [],
                     "top1_value": fitted, "top1_correct": correct, "param_rel_error": rel,
                     "heldout_error_reduction": d.explained_fraction.get(joint),
                     "flagged_failing": joint in d.explained_fraction})
    acc = float(np.mean([r["top1_correct"] for r in rows]))
    rel_errs = [r["param_rel_error"] for r in rows if r["param_rel_error"] is not None]
    out = {"benchmark": "sysid_diagnosis", "seed": a.seed, "joints": len(JOINT_NAMES),
           "sequences": rec.num_sequences, "verdict": d.verdict, "top1_accuracy": acc,
           "param_rel_error_median": float(np.median(rel_errs)) if rel_errs else None,
           "param_rel_error_max": float(np.max(rel_errs)) if rel_errs else None,
           "params_within_10pct": float(np.mean([e <= 0.1 for e in rel_errs])) if rel_errs else None,
           "heldout_reduction_median": float(np.median([r["heldout_error_reduction"] for r in rows
                                                        if r["heldout_error_reduction"] is not None])),
           "simulate_seconds": t_sim, "diagnosis_seconds": t_diag, "diagnosis_cpu_seconds": c_diag,
           "stage_seconds": d.stage_times_s, "stage_cpu_seconds": d.to_dict().get("stage_cpu_s"),
           "target_seconds": 300,
           "target_met": bool(t_diag <= 300), "cases": rows}
    write_result(a.out, out, name="sysid_diagnosis", force=a.force, indent=2)
    print(f"{'joint':<8} {'truth':<18} {'value':>8}  {'top-1':<18} {'fitted':>8}  {'ok':<3} {'held-out red.':>13}")
    for r in rows:
        print(f"{r['joint']:<8} {r['truth_effect']:<18} {r['truth_value']:8.4g}  {str(r['top1_effect']):<18} "
              f"{(r['top1_value'] if r['top1_value'] is not None else float('nan')):8.4g}  "
              f"{'yes' if r['top1_correct'] else 'NO':<3} "
              f"{(r['heldout_error_reduction'] if r['heldout_error_reduction'] is not None else float('nan')):13.3f}")
    print("stages (s): " + ", ".join(f"{k} {v:.1f}" for k, v in d.stage_times_s.items()))
    print(f"verdict {d.verdict}; top-1 accuracy {acc:.2f}; parameters within 10 %: {out['params_within_10pct']}; "
          f"median rel. error {out['param_rel_error_median']}; diagnosis {t_diag:.0f} s ({c_diag:.0f} s CPU) for {rec.num_sequences} "
          f"sequences (target 300 s: {'met' if out['target_met'] else 'NOT met'}); wrote {a.out}")
    return out


if __name__ == "__main__":
    main()
