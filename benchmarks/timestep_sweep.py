"""Which physics timestep? Run the soundness checks at several steps (control fixed at 12 Hz).

For each timestep: every registry object dropped on the table (worst penetration, objects still
moving after 2 s, simulator warnings) and the scripted grasp of the 5 cm cube at several squeeze
depths (lift achieved, slip in the palm). adadex uses the largest step at which all pass.

    python benchmarks/timestep_sweep.py [--hz 60 90 120] [--out FILE]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from _data import check_result, write_result
from adadex.sim import objects
from adadex.sim.grasp import scripted_grasp_lift
from adadex.sim.scene import OBJECT_QPOS, PhysicsOptions, build_scene_model, home_state

RESULTS = Path(__file__).resolve().parent / "results"


def settle_stats(name: str, opts: PhysicsOptions) -> dict:
    model = build_scene_model(name, options=opts)
    data = mujoco.MjData(model)
    qpos, ctrl = home_state(model)
    data.qpos[:] = qpos
    data.qpos[OBJECT_QPOS.start + 2] += 0.01
    data.ctrl[:] = ctrl
    n = int(round(2.0 / opts.timestep))
    pen = 0.0
    for i in range(n):
        mujoco.mj_step(model, data)
        if i > n // 2 and data.ncon:
            pen = max(pen, float(-data.contact.dist[: data.ncon].min()))
    return {"penetration_m": pen, "speed_m_s": float(np.linalg.norm(data.qvel[22:25])),
            "warnings": int(sum(w.number for w in data.warning))}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hz", type=float, nargs="+", default=[60.0, 90.0, 120.0])
    p.add_argument("--squeeze", type=float, nargs="+", default=[0.004, 0.008, 0.012, 0.016])
    p.add_argument("--out", type=Path, default=RESULTS / "timestep_sweep.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name="timestep_sweep", force=a.force)      # before any work: refuse a file not ours
    rows = []
    for hz in a.hz:
        opts = PhysicsOptions(timestep=1.0 / hz)
        t0 = time.perf_counter()
        settle = {n: settle_stats(n, opts) for n in tqdm(objects.OBJECT_NAMES, desc=f"{hz:.0f} Hz settle")}
        grasps = []
        for sq in a.squeeze:
            g = scripted_grasp_lift("cube_050", squeeze=sq, model=build_scene_model("cube_050", options=opts))
            grasps.append({"squeeze_m": sq, "lift_m": g.lift_achieved, "slip_m": g.max_slip,
                           "held": bool(g.lift_achieved > 0.09 and g.max_slip < 0.02)})
        settle_ok = all(s["penetration_m"] < 0.002 and s["speed_m_s"] < 0.01 and s["warnings"] == 0
                        for s in settle.values())
        rows.append({
            "physics_hz": hz, "timestep": opts.timestep,
            "worst_penetration_m": max(s["penetration_m"] for s in settle.values()),
            "objects_not_settled": [n for n, s in settle.items() if s["speed_m_s"] >= 0.01],
            "warnings": sum(s["warnings"] for s in settle.values()),
            "settle_ok": settle_ok, "grasps": grasps,
            "all_grasps_held": all(g["held"] for g in grasps),
            "passes": bool(settle_ok and all(g["held"] for g in grasps)),
            "wall_s": time.perf_counter() - t0,
        })
    passing = [r["physics_hz"] for r in rows if r["passes"]]
    out = {"benchmark": "timestep_sweep", "control_hz": 12.0, "rows": rows,
           "lowest_passing_physics_hz": min(passing) if passing else None}
    write_result(a.out, out, name="timestep_sweep", force=a.force, indent=2)
    print(f"{'Hz':>5} {'pen mm':>7} {'settled':>8} {'grasps held (lift cm / slip mm)':<50} pass")
    for r in rows:
        gs = " ".join(f"{100 * g['lift_m']:.1f}/{1000 * g['slip_m']:.0f}" for g in r["grasps"])
        print(f"{r['physics_hz']:5.0f} {1000 * r['worst_penetration_m']:7.2f} {str(r['settle_ok']):>8} "
              f"{gs:<50} {r['passes']}")
    print(f"largest passing timestep: 1/{out['lowest_passing_physics_hz']:.0f} s; wrote {a.out}")
    return out


if __name__ == "__main__":
    main()
