"""``adadex sysid demo``: the whole workbench loop on the shipped demo recording.

compare → where it fails → diagnose → add the selected effects → the error falls → the paper's
kp/kd identification on the failing joints, for comparison → HTML report.
The recording (``assets/recordings/demo.npz``) was made with hidden effects; nothing in it or in
this code names them — the loop has to find them.

The output folder is written as one unit (:func:`adadex.io.output_folder`, kind ``sysid-demo``): an
existing ``out`` that is not an earlier demo output (a folder of the user's files, a file) is refused
before any work unless ``force``.
"""

from __future__ import annotations

import time
from pathlib import Path

from adadex.data.recording import load_recording
from adadex.io import output_folder
from adadex.progress import progress_bar
from adadex.sysid.compare import compare, localize
from adadex.sysid.diagnose import diagnose
from adadex.sysid.fit import identify_pd, sequences_moving
from adadex.sim.model_source import ModelSource
from adadex.sysid.replay import Replayer
from adadex.sysid.report import error_stages, write_report


DEMO_KIND = "sysid-demo"


def run_demo(recording, out="adadex_demo", nthread: int = 2, model=None, force: bool = False) -> dict:
    """Walk the loop on ``recording`` (a path; ``adadex sysid demo`` passes the shipped demo recording),
    writing the diagnosis, the patch and the report under ``out``. The caller names the recording, so
    this module needs nothing from the CLI (which imports it). ``out`` is replaced only when it is an
    earlier demo output (its marker) or with ``force``; checked before any work.

    Each step's results are printed as it goes.

    Args:
        recording: the recording's path (an ``.npz`` file, a ``.csv`` file or a folder of them;
            :func:`~adadex.data.recording.load_recording`).
        out: the output folder (default ``"adadex_demo"``), written as one unit:
            ``diagnosis/diagnosis.json``, ``patch.json`` (the selected effects) and ``report.html``
            (:func:`~adadex.sysid.report.write_report`).
        nthread: threads of the replays' rollout pools (default 2).
        model: the user's MJCF file the recording was made on; None (default): adadex's robot.
        force: replace an existing ``out`` that is not an earlier demo output (default False).

    Returns:
        a dict: ``verdict`` (the diagnosis'), ``stages`` (the error stages,
        :meth:`~adadex.sysid.report.Stages.to_dict`) and ``seconds`` (the loop's wall time, s).
    """
    out = Path(out)
    with output_folder(out, DEMO_KIND, force=force) as tmp:
        result = _run(recording, out, tmp, nthread, model)
    print(f"\nreport: {out / 'report.html'}   ({result['seconds']:.0f} s)")
    return result


def _run(recording, out: Path, tmp: Path, nthread: int, model) -> dict:
    """The loop; files go to ``tmp`` (renamed to ``out`` when complete), messages name ``out``."""
    t0 = time.perf_counter()
    rec = load_recording(recording, robot=None if model is None else ModelSource(model).robot())
    print(f"adadex sysid demo: {rec.num_sequences} sequences × {rec.duration:.1f} s at {1 / rec.dt:.0f} Hz on "
          f"{len(rec.joint_names)} joints ({', '.join(rec.joint_names)})\n")
    rep = Replayer(rec, nthread=nthread)

    print("1. compare: replay every sequence on the nominal model")
    cmp0 = compare(rec, replayer=rep)
    print(f"   overall RMS error {cmp0.rms() * 57.2958:.3f}°")
    print("\n2. where it fails")
    loc = localize(cmp0)
    for s in loc.sentences:
        print("   " + s)

    print("\n3. diagnose: fit every candidate effect where it fails, rank on held-out sequences")
    d = diagnose(rec, nthread=nthread)
    d.save(tmp / "diagnosis")
    for f in d.findings[-len(d.explained_fraction) - (d.verdict == "unexplained"):]:
        print("   " + f)
    print(f"   verdict: {d.verdict}")

    patch = d.patch(rep.robot)
    patch.save(tmp / "patch.json")
    print(f"\n4. add: {patch.describe()}  → {out / 'patch.json'}")

    print("\n5. the error falls")
    st = error_stages(rec, patch, replayer=rep)
    for line in st.table().splitlines():
        print("   " + line)
    # A healthy joint's error is its noise floor: a gain fit there has nothing to absorb (CMA-ES made
    # no progress on any of the demo's four, at 130 replays each: two thirds of the demo's time).
    pd_joints = loc.failing_joints
    print("\n6. the paper's identification for comparison: per-joint kp/kd scales, CMA-ES vs least squares, "
          f"on the joints where the model fails ({', '.join(pd_joints) or 'none'})")
    pd = []
    for joint in progress_bar(pd_joints, desc="kp/kd fits", unit="joint"):
        for method in ("cma", "lsq"):
            pd.append(identify_pd(rep, joint, sequences_moving(rec, joint), method=method, max_evals=120))
    for r in pd:
        print(f"   {r['joint']:<7} {r['method']:<4} kp×{r['kp_scale']:.3f} kd×{r['kd_scale']:.3f}  MSE "
              f"{r['mse_nominal']:.2e} → {r['mse']:.2e} rad²  ({r['evaluations']} replays, {r['seconds']:.1f} s)"
              + ("" if r.get("progress", True) else "  no progress: the nominal model is kept"))
    write_report(rec, patch, tmp / "report.html", diagnosis=d, stages=st, pd_results=pd)
    dt = time.perf_counter() - t0
    return {"verdict": d.verdict, "stages": st.to_dict(), "seconds": dt}
