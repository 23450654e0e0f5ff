"""Does kinematic replay carry the object? Where a specialist's object error comes from, per reference.

On one semantic group's references, with nominal physics (no randomization), two open-loop
controllers through the PD servos:

* ``replay``: the reference joints (:func:`adadex.envs.replay.replay_policy`);
* ``squeeze``: the same with the finger flexion targets held ``--squeeze`` rad further closed, so the
  position servos press on whatever the fingers touch (a grip the reference's surface-contact
  fingers cannot give).

For each reference: the object's largest rise above its start (``lift_mm``), how far it was moved on
the table before the reference starts lifting it (``pushed_cm``: the approach and closing pushed it
away), mean T_o and completion, and how far the servos lag the reference before the lift
(``arm_lag_rad``: the largest arm-joint error; ``palm_lag_cm``: the palm's distance from where the
reference joints put it). Per reference, kinematically, the order in which the fingertips reach
the object while the hand closes (``touch_frames``: frames after the grasp phase starts at which
each fingertip is first within 2 mm of the object at its start pose): a digit that touches alone
for a few frames pushes the object across the table before the others arrive. Beside them,
:func:`adadex.sim.grasp.scripted_grasp_lift` on the group's object, squeezed along x and, if that
does not lift it, across (a planned fingertip grasp: can this hand lift this object at all?), and
how deep the references' own hand sits inside the object
while holding it (kinematically, the deepest link off the distal phalanges and each fingertip's
median depth; a dataset built with ``adadex data build --contact`` keeps the first at zero and the
tips at its squeeze). With ``--contacts``, each reference is also replayed in one plain MuJoCo world
(same start, same servo targets and per-step action bound as the env) to list what touches the
object while the fingers close (:func:`adadex.sim.contacts.body_contact_forces`): which hand links,
how hard, how hard the table pushes back, and how far the object has moved by the reference's lift;
``--trace`` (implies ``--contacts``) prints, step by step from the grasp, where the object is and
every force on it. Writes ``benchmarks/results/replay_grasp.json``.

    python benchmarks/replay_grasp.py [--dataset data/small] [--group G] [--squeeze 0.2] [--contacts [--trace]]
    python benchmarks/replay_grasp.py [--dataset data/small] --all-groups

``--all-groups`` instead replays every training reference and grasps every object, and prints one line
per group: how many of its references replay carries (the object rises at least half as high as the
reference's) and whether the scripted grasp lifts its object; writes ``replay_grasp_groups.json``.

The group defaults to ``benchmarks/specialist_quality.py``'s (the first of the largest).
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from _data import RESULTS, check_result, refuse, write_result

#: the object counts as lifted by the reference once it is this far above its start (m)
REF_LIFT = 0.01


def _per_reference(rollout, per_reference: dict) -> list[dict]:
    """Lift, pre-lift push, T_o and completion of each world of an ``evaluate`` rollout ([B, T])."""
    nxt = rollout["next"]
    obj = nxt["object", "pose"][..., :3]
    ref = nxt["reference", "object_pose"][..., 0, :3]
    arm_err = (nxt["proprio", "joint_pos"] - nxt["reference", "hand_joint_pos"][..., 0, :])[..., :6].abs().amax(-1)
    palm_err = (nxt["proprio", "link_pose"][..., 0, :3] - nxt["reference", "hand_link_pose"][..., 0, 0, :3]).norm(dim=-1)
    start = obj[:, 0]
    out = []
    for w, (name, m) in enumerate(per_reference):
        rising = (ref[w, :, 2] - ref[w, 0, 2]) > REF_LIFT
        t_lift = int(rising.float().argmax()) if bool(rising.any()) else obj.shape[1] - 1
        out.append({"reference": name, "lift_mm": 1000 * float((obj[w, :, 2] - start[w, 2]).max()),
                    "reference_rise_mm": 1000 * float((ref[w, :, 2] - ref[w, 0, 2]).max()),
                    "pushed_cm": 100 * float((obj[w, t_lift, :2] - start[w, :2]).norm()),
                    "reference_lift_step": t_lift, "T_o_cm": 100 * m["T_o"], "completion_pct": 100 * m["completion"],
                    "arm_lag_rad": float(arm_err[w, :t_lift + 1].max()),
                    "palm_lag_cm": 100 * float(palm_err[w, :t_lift + 1].max())})
    return out


def _touch_frames(ds, index: int, touch: float = 0.002) -> dict:
    """Frames after the grasp phase starts at which each fingertip first comes within ``touch`` m of
    the object, posed at its episode start (where the object is until the hand moves it), up to
    the reference's lift; ``None``: not before the lift."""
    from adadex.data.object_contact import TIP_GEOMS, hand_object_overlap

    ref, entry = ds[index], ds.entries[index]
    phases = ref.meta.get("phases")
    if not phases:
        return {"reference": entry["name"], "skipped": "no grasp phases in its metadata"}
    frames = slice(phases["grasp"], phases["manipulate"] + 1)
    q = ref.hand_joint_pos[frames]
    pose = np.repeat(ref.object_pose[entry["window_start"]][None], len(q), axis=0)
    depth = hand_object_overlap(q, pose, ref.object_name)
    first = {n: int(np.argmax(depth[n] > -touch)) if bool((depth[n] > -touch).any()) else None for n in TIP_GEOMS}
    return {"reference": entry["name"], "touch_frames": first}


def _closing_contacts(ds, index: int, after: int = 8) -> dict:
    """Replay reference ``index`` in one MuJoCo world from its episode start to ``after`` steps past
    the reference's lift; the hand's contact forces on the object while the fingers close (peak per
    link, N), the table's force before closing and its peak, and the object's travel; ``trace``: per
    control step from the grasp phase on, the object's displacement from its start (cm) and every
    force on it above 0.05 N (what showed the closing hand pressing objects down and out)."""
    import mujoco

    from adadex.envs.tracking import TrackingConfig
    from adadex.sim.contacts import body_contact_forces
    from adadex.sim.robot import NUM_JOINTS, joint_limits
    from adadex.sim.scene import CONTROL_HZ, OBJECT_BODY, OBJECT_QPOS, build_scene_model

    ref, entry = ds[index], ds.entries[index]
    start = entry["window_start"]
    phases = ref.meta.get("phases")
    if not phases:
        return {"reference": entry["name"], "skipped": "no grasp phases in its metadata"}
    grasp, lift = phases["grasp"] - start, phases["manipulate"] - start
    cfg, lim = TrackingConfig(), joint_limits()
    m = build_scene_model(ref.object_name)
    d = mujoco.MjData(m)
    target = np.clip(ref.hand_joint_pos[start].astype(float), lim[:, 0], lim[:, 1])
    d.qpos[:NUM_JOINTS] = target
    d.qpos[OBJECT_QPOS] = ref.object_pose[start] + np.r_[0, 0, cfg.object_lift, 0, 0, 0, 0]
    d.ctrl[:] = target
    mujoco.mj_forward(m, d)
    substeps = int(round(1.0 / (CONTROL_HZ * m.opt.timestep)))
    obj0 = d.qpos[OBJECT_QPOS][:3].copy()
    hand_peak, table = {}, {"before": 0.0, "peak": 0.0}
    moved, touching_after, trace = {}, [], []
    for t in range(min(lift + after, ref.num_frames - start - 1)):
        step = np.clip(ref.hand_joint_pos[start + t + 1] - target, -cfg.max_action, cfg.max_action)
        target = np.clip(target + step, lim[:, 0], lim[:, 1])
        d.ctrl[:] = target
        for _ in range(substeps):
            mujoco.mj_step(m, d)
        forces = body_contact_forces(m, d, OBJECT_BODY)
        if t >= grasp - 1:
            trace.append({"step": t + 1, "object_cm": [round(100 * float(x), 2) for x in d.qpos[OBJECT_QPOS][:3] - obj0],
                          "forces_N": {k: round(float(v), 2) for k, v in sorted(forces.items(), key=lambda kv: -kv[1])
                                       if v > 0.05}})
        if t == grasp - 1:
            table["before"] = forces.get("table", 0.0)
        if grasp <= t <= lift:
            table["peak"] = max(table["peak"], forces.get("table", 0.0))
            for name, f in forces.items():
                if name != "table":
                    hand_peak[name] = max(hand_peak.get(name, 0.0), f)
        if t in (lift, lift + after - 1):
            moved["at_lift" if t == lift else "after"] = 100 * float(np.linalg.norm(d.qpos[OBJECT_QPOS][:2] - obj0[:2]))
        if t == lift + after - 1:
            touching_after = sorted(n for n in forces if n != "table")
    return {"reference": entry["name"], "hand_peak_N": dict(sorted(hand_peak.items(), key=lambda kv: -kv[1])),
            "table_before_N": table["before"], "table_peak_N": table["peak"],
            "moved_at_lift_cm": moved.get("at_lift"), "steps_after_lift": after, "moved_after_cm": moved.get("after"),
            "hand_touching_then": touching_after, "grasp_step": grasp, "lift_step": lift, "trace": trace}


def _hold_overlap(ds, index: int) -> dict:
    """How deep the reference's own hand sits inside the object during the hold (kinematic, MuJoCo's
    collision detection): the deepest link off the distal phalanges, and the fingertips' median depths."""
    from adadex.data.object_contact import PAD_GEOMS, TIP_GEOMS, hand_object_overlap

    ref, name = ds[index], ds.entries[index]["name"]
    phases = ref.meta.get("phases")
    if not phases:
        return {"reference": name, "skipped": "no grasp phases in its metadata"}
    hold = slice(phases["manipulate"], phases["release"])
    depth = hand_object_overlap(ref.hand_joint_pos[hold], ref.object_pose[hold], ref.object_name)
    deepest = max((n for n in depth if n not in TIP_GEOMS + PAD_GEOMS), key=lambda n: depth[n].max())
    return {"reference": name, "deepest_link": deepest, "deepest_link_mm": 1000 * float(depth[deepest].max()),
            "tip_median_mm": {n: 1000 * float(np.median(depth[n])) for n in TIP_GEOMS}}


def _contacts_line(row: dict) -> str:
    if "skipped" in row:
        return f"  {row['reference']}: skipped ({row['skipped']})"
    links = ", ".join(f"{n} {f:.1f} N" for n, f in row["hand_peak_N"].items() if f >= 0.1) or "nothing"
    return (f"  {row['reference']}: closing, the object is touched by {links}; table {row['table_before_N']:.1f} → "
            f"{row['table_peak_N']:.1f} N; moved {row['moved_at_lift_cm']:.1f} cm by the lift, "
            f"{row['moved_after_cm']:.1f} cm {row['steps_after_lift']} steps later; hand links on it then: "
            f"{', '.join(row['hand_touching_then']) or 'none'}")


#: the scripted grasp counts as lifting the object once it holds it this high (m)
SCRIPTED_LIFT = 0.05


def _scripted(object_name: str) -> dict:
    """The scripted pinch of ``object_name`` along x (away from the robot) and, unless that lifts it
    ``SCRIPTED_LIFT`` high, across (y): the better of the two (a lift first, then no fling)."""
    from adadex.sim.grasp import scripted_grasp_lift
    from adadex.sim.ik import IKError

    tries = []
    for axis in ("x", "y"):
        try:
            g = scripted_grasp_lift(object_name, axis=axis)
            tries.append({"axis": axis, "lift_cm": 100 * g.lift_achieved, "max_slip_cm": 100 * g.max_slip,
                          "unstable": g.unstable})
        except IKError as e:                  # the script's arm motion is out of reach for this object
            tries.append({"axis": axis, "lift_cm": None, "unstable": False, "error": str(e)})
        if not tries[-1]["unstable"] and (tries[-1]["lift_cm"] or 0.0) >= 100 * SCRIPTED_LIFT:
            break
    return max(tries, key=lambda t: (not t["unstable"] and (t["lift_cm"] or 0.0) >= 100 * SCRIPTED_LIFT,
                                     t["lift_cm"] is not None and not t["unstable"], t["lift_cm"] or -1e9))


def _scripted_text(g: dict) -> str:
    if g["unstable"]:
        return "flings it"
    if g["lift_cm"] is None:
        return "has no plan"
    return f"lifts {g['lift_cm']:.1f} cm" + (f", slip {g['max_slip_cm']:.1f} cm" if "max_slip_cm" in g else "") + \
        f" (squeezing along {g['axis']})"


def _all_groups(ds, refs: list[int], out_path: Path, force: bool = False) -> dict:
    """Kinematic replay of every reference (nominal physics) and the scripted grasp of every object:
    per semantic group, how many references the replay carries (the object rises at least half as
    high as the reference's; only references whose object rises more than ``REF_LIFT``) and whether
    this hand can lift the group's object at all."""
    from adadex.envs.replay import replay_policy
    from adadex.eval.evaluate import evaluate
    res = evaluate(replay_policy(), ds, references=refs, keep_rollouts=True, progress=True)
    items = list(res["per_reference"].items())
    rows = [r for k, roll in enumerate(res["rollouts"])
            for r in _per_reference(roll, items[64 * k: 64 * (k + 1)])]
    by_group: dict[int, list] = {}
    for i, r in zip(refs, rows):
        by_group.setdefault(int(ds.entries[i]["group"]), []).append((i, r))
    groups, grasps = [], {}
    for g, members in sorted(by_group.items()):
        name = ds.entries[members[0][0]]["object"]
        if name not in grasps:
            grasps[name] = _scripted(name)
        rising = [r for _, r in members if r["reference_rise_mm"] > 1000 * REF_LIFT]
        groups.append({"group": g, "object": name, "instruction": ds.entries[members[0][0]]["instruction"],
                       "references": len(members), "rising": len(rising),
                       "carried": sum(r["lift_mm"] >= 0.5 * r["reference_rise_mm"] for r in rising),
                       "lift_mm": [round(r["lift_mm"], 1) for _, r in members],
                       "T_o_cm": float(np.mean([r["T_o_cm"] for _, r in members])),
                       "scripted_grasp": grasps[name]})
        gr = grasps[name]
        print(f"group {g:3d} {name:13s} {groups[-1]['instruction'][:44]:44s} replay carries "
              f"{groups[-1]['carried']}/{len(rising)} rising (lifts " + ", ".join(f"{v:.0f}" for v in groups[-1]["lift_mm"])
              + " mm); scripted grasp " + _scripted_text(gr))
    liftable = [n for n, gr in grasps.items() if not gr["unstable"] and (gr["lift_cm"] or 0.0) >= 100 * SCRIPTED_LIFT]
    out = {"references": len(refs), "rising": sum(g["rising"] for g in groups),
           "carried": sum(g["carried"] for g in groups), "objects": len(grasps),
           "objects_the_scripted_grasp_lifts": sorted(liftable), "groups": groups}
    print(f"replay carries {out['carried']} of the {out['rising']} references whose object rises "
          f"({len(refs)} references, {len(groups)} groups); the scripted grasp lifts {len(liftable)} of "
          f"{len(grasps)} objects ≥ {100 * SCRIPTED_LIFT:.0f} cm (along x or across)")
    write_result(out_path, out, name="replay_grasp", force=force, indent=1)
    print(f"wrote {out_path}")
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=Path("data/small"))
    p.add_argument("--group", type=int, default=None)
    p.add_argument("--squeeze", type=float, default=0.2, help="rad added to the finger flexion targets")
    p.add_argument("--contacts", action="store_true", help="list the contacts on the object while the fingers close")
    p.add_argument("--trace", action="store_true",
                   help="--contacts, and each reference's object motion and forces step by step from the grasp")
    p.add_argument("--all-groups", action="store_true",
                   help="instead: replay every training reference and grasp every object, one line per group")
    p.add_argument("--out", type=Path, default=None,
                   help="default: results/replay_grasp.json (replay_grasp_groups.json with --all-groups)")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    a.out = a.out or RESULTS / ("replay_grasp_groups.json" if a.all_groups else "replay_grasp.json")
    check_result(a.out, name="replay_grasp", force=a.force)      # before any work: refuse a file not ours
    torch.set_num_threads(1)

    from tensordict.nn import TensorDictModule

    from adadex.data.reference import ReferenceDataset
    from adadex.envs.observation import JOINT_TARGET, REF_JOINT_POS
    from adadex.envs.replay import replay_policy
    from adadex.envs.tracking import episode_references
    from adadex.eval.evaluate import evaluate
    from adadex.sim.robot import JOINT_NAMES

    if not (a.dataset / "index.json").exists():
        raise refuse("replay_grasp", f"{a.dataset}: no dataset there (adadex data build --preset small --out {a.dataset})")
    ds = ReferenceDataset(a.dataset)
    train_refs = episode_references(ds, ("unseen_trajectory", "train"))
    if a.all_groups:
        return _all_groups(ds, train_refs, a.out, a.force)
    counts = Counter(ds.entries[i]["group"] for i in train_refs)
    group = a.group if a.group is not None else min(g for g, n in counts.items() if n == max(counts.values()))
    refs = [i for i in train_refs if ds.entries[i]["group"] == group]
    if not refs:
        raise refuse("replay_grasp", f"group {group} has no training reference with an episode window in {a.dataset}")
    obj_name = ds.entries[refs[0]]["object"]
    print(f"group {group}: {len(refs)} references ({ds.entries[refs[0]]['instruction']!r} on {obj_name}), "
          f"nominal physics")

    flexion = torch.tensor([float(n.endswith(("_mcp", "_pip", "_dip")) or n in ("th_cmc", "th_axl", "th_ipl"))
                            for n in JOINT_NAMES])
    squeeze = a.squeeze * flexion
    controllers = {"replay": replay_policy(),
                   "squeeze": TensorDictModule(lambda q_ref, q_target: q_ref[..., 1, :] + squeeze - q_target,
                                               in_keys=[REF_JOINT_POS, JOINT_TARGET], out_keys=["action"])}
    out = {"group": group, "object": obj_name, "squeeze_rad": a.squeeze}
    for name, policy in controllers.items():
        res = evaluate(policy, ds, references=refs, keep_rollouts=True, progress=False)
        rows = _per_reference(res["rollouts"][0], list(res["per_reference"].items()))
        out[name] = {"per_reference": rows, "T_o_cm": res["summary"]["T_o"],
                     "completion_pct": res["summary"]["completion_pct"]}
        print(f"{name:8s} T_o {res['summary']['T_o']:.1f} cm, completion {res['summary']['completion_pct']:.1f} % | "
              + ", ".join(f"lift {r['lift_mm']:.0f} mm pushed {r['pushed_cm']:.1f} cm" for r in rows))
        print(f"{'':8s} servo lag before the lift: arm joints ≤ " + ", ".join(f"{r['arm_lag_rad']:.3f}" for r in rows)
              + " rad; palm ≤ " + ", ".join(f"{r['palm_lag_cm']:.1f}" for r in rows) + " cm")
    out["hold_overlap"] = [_hold_overlap(ds, i) for i in refs]
    print("the references' hand inside the object while holding it (kinematic): " + "; ".join(
        f"{r['deepest_link']} {r['deepest_link_mm']:.0f} mm, tips "
        + "/".join(f"{v:.0f}" for v in r["tip_median_mm"].values()) + " mm" if "skipped" not in r else "skipped"
        for r in out["hold_overlap"]))
    out["touch_frames"] = [_touch_frames(ds, i) for i in refs]
    print("fingertips reaching the object, frames after the grasp phase starts (thumb/index/middle/ring): " + "; ".join(
        "/".join("-" if v is None else str(v) for v in r["touch_frames"].values()) if "skipped" not in r else "skipped"
        for r in out["touch_frames"]))
    out["scripted_grasp"] = _scripted(obj_name)
    print(f"scripted grasp-and-lift of {obj_name}: " + _scripted_text(out["scripted_grasp"]))
    if a.contacts or a.trace:
        out["closing_contacts"] = [_closing_contacts(ds, i) for i in refs]
        for row in out["closing_contacts"]:
            print(_contacts_line(row))
            if a.trace and "trace" in row:
                for r in row["trace"]:
                    mark = " (grasp)" if r["step"] == row["grasp_step"] else " (lift)" if r["step"] == row["lift_step"] else ""
                    print(f"    step {r['step']:3d}{mark}: object moved ({', '.join(f'{x:5.1f}' for x in r['object_cm'])}) cm; "
                          + (", ".join(f"{k} {v:.1f} N" for k, v in r["forces_N"].items()) or "nothing touches it"))
    write_result(a.out, out, name="replay_grasp", force=a.force, indent=1)
    print(f"wrote {a.out}")
    return out


if __name__ == "__main__":
    main()
