"""``adadex sysid …``: the model-versus-measurement loop from the command line.

    adadex sysid excite   --joints if_pip,if_dip --out plan.npz
    adadex sysid simulate plan.npz --patch truth.json --noise 2e-4 --out rec.npz
    adadex sysid compare  rec.npz [--patch patch.json] [--out DIR]
    adadex sysid diagnose rec.npz --out D
    adadex sysid fit      rec.npz --add coulomb_friction:if_pip,if_dip --out patch.json   (or --accept D)
    adadex sysid report   rec.npz --patch patch.json [--diagnosis D] --out report.html
    adadex sysid demo     [--out DIR]    the whole loop on assets/recordings/demo.npz

``fit --accept D`` turns diagnosis D's selected effects into a patch (added to ``--patch``, if given).
On a diagnosis that selected nothing (verdict ``nothing_missing``, or ``unexplained`` with no effect
chosen) it says "nothing to add" and writes the starting patch unchanged — ``--patch``'s effects, else
a patch with no effects — so a script's next step finds the file; the exit code is 0.

Output folders (compare, diagnose) are written as one unit and replace only an earlier output of the
same command; an existing --out that is something else (your files, another kind of output) is
refused unless --force, checked before any work starts.

Every command takes ``--model PATH``: replay on that MJCF (its servoed joints by name, its own
options and contacts) instead of the built-in scene; patches made on it record it and are refused
on another model. ``adadex sim export --out world.xml`` writes the built-in world as such a file.

The demo's folder and excite's CSV folder are guarded the same way. Output files (excite's plan,
simulate's recording) carry a marker beside them (``.NAME.adadex-output.json``): an existing file
is replaced only when its marker says the same command wrote it, unchanged since, or with --force.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from adadex.data.recording_errors import RecordingError
from adadex.errors import AdadexError
from adadex.io import check_output, check_output_file, output_file, output_folder
from adadex.resources import asset
from adadex.sim.effects import EFFECT_NAMES
from adadex.sim.model_source import same_model
from adadex.sim.patch import ModelPatch, PatchError

DEMO_RECORDING = asset("recordings", "demo.npz")


class CliError(AdadexError):
    """A user error: printed as one line, exit code 2."""


def _robot(model):
    """The joint table of the ``--model`` file (None: the built-in robot)."""
    if not model:
        return None
    from adadex.sim.model_source import ModelSource

    return ModelSource(model).robot()


def _load_rec(path, model=None):
    from adadex.data.recording import load_recording, prefixed

    rec = load_recording(path, robot=_robot(model))
    try:
        return rec.check_measured_range()     # 1e6 rad is no measurement: refused before any replay
    except RecordingError as e:
        raise prefixed(e, path) from None


def _load_patch(path, model=None) -> ModelPatch:
    robot = _robot(model)
    if not path:
        return ModelPatch(robot=robot)
    try:
        return ModelPatch.load(path, robot=robot)
    except PatchError:
        raise
    except (OSError, ValueError, TypeError) as e:    # a folder, bad UTF-8, a value that is not a number
        raise CliError(f"{path}: not a readable model patch ({type(e).__name__}: {e})") from None


#: What an earlier output folder of each command looks like when it was written before markers existed.
#: The single files (patches, reports, recordings, plans) are recognized by their marker only: a user's
#: own JSON with ``effects`` or ``.npz`` with the recording's keys looks the same inside.
_RECOGNIZE = {"compare": lambda p: (p / "compare.json").is_file(), "diagnosis": lambda p: (p / "diagnosis.json").is_file()}


def _check_out(a, kind: str) -> None:
    """Refuse ``a.out`` before any work if it is not an earlier output of this kind (``--force`` replaces it)."""
    if a.out:
        if kind in _RECOGNIZE:
            check_output(a.out, kind, force=a.force, recognize=_RECOGNIZE[kind])
        else:
            check_output_file(a.out, kind, force=a.force)


def _floats(text: str, option: str) -> tuple[float, ...]:
    """Comma-separated numbers of ``option``; anything else is one line naming the option."""
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise CliError(f"{option}: expected comma-separated numbers such as 0.5,1.5,3, got {text!r}") from None


def _cmd_excite(a) -> int:
    from adadex.sysid.excite import design_excitation

    out = Path(a.out)
    folder = out.with_suffix("") if out.suffix == ".csv" else None
    if folder is not None:              # before any work: a folder of CSV files, or one .npz file
        check_output(folder, "plan", force=a.force)
    else:
        check_output_file(out, "plan", force=a.force)
    plan = design_excitation(a.joints.split(","), freqs=_floats(a.freqs, "--freqs"), amps=_floats(a.amps, "--amps"),
                             poses=tuple(a.poses.split(",")), kinds=tuple(a.kinds.split(",")),
                             duration=a.duration, rate=a.rate, robot=_robot(a.model))
    if folder is not None:
        from adadex.data.recording import to_csv

        with output_folder(folder, "plan", force=a.force) as tmp:
            files = to_csv(plan.to_recording(plan.command.copy(), {"plan": True}), tmp)
        print(f"wrote {len(files)} CSV files to {folder}/")
    else:
        with output_file(out, "plan", force=a.force):
            plan.save(out)
        print(f"wrote {out}: {len(plan.sequences)} sequences × {len(plan.time)} samples at {a.rate:g} Hz "
              f"on {', '.join(plan.joint_names)}")
    return 0


def _cmd_simulate(a) -> int:
    from adadex.sysid.excite import ExcitationPlan, simulate_recording

    check_output_file(a.out, "recording", force=a.force)
    plan = ExcitationPlan.load(a.plan, robot=_robot(a.model))
    rec = simulate_recording(plan, _load_patch(a.patch, a.model), noise=a.noise, seed=a.seed, nthread=a.threads)
    with output_file(a.out, "recording", force=a.force):
        rec.save(a.out)
    print(f"wrote {a.out}: {rec.num_sequences} sequences simulated"
          + (f" with {len(_load_patch(a.patch, a.model))} effect(s)" if a.patch else " on the nominal model")
          + f", sensor noise {a.noise:g} rad, seed {a.seed}")
    return 0


def _print_stages(rec, patch, threads):
    """Print baseline → +each effect and return the :class:`~adadex.sysid.report.Stages`."""
    from adadex.sysid.report import error_stages

    st = error_stages(rec, patch, nthread=threads)
    print(st.table())
    return st


def _cmd_compare(a) -> int:
    from adadex.sysid.compare import compare, localize

    rec = _load_rec(a.recording, a.model)
    patch = _load_patch(a.patch, a.model)
    _check_out(a, "compare")
    cmp0 = compare(rec, nthread=a.threads)
    loc = localize(cmp0)
    print(loc.text)
    st = None
    if a.patch:
        print(f"\nwith {a.patch}: {patch.describe()}")
        st = _print_stages(rec, patch, a.threads)
    if a.out:
        from adadex.sysid import plots

        out = Path(a.out)
        summary = {"nominal": cmp0.summary(), "localization": loc.to_dict()}
        if st is not None:
            summary["stages"] = st.to_dict()
        err = cmp0.rms_per_sequence_joint()
        s, j = np.unravel_index(np.argmax(err), err.shape)
        sims = {"model (nominal)": cmp0.simulated}
        if st is not None:
            sims["model + patch"] = st.comparisons[-1].simulated
        with output_folder(out, "compare", force=a.force, recognize=_RECOGNIZE["compare"]) as tmp:
            (tmp / "compare.json").write_text(json.dumps(summary, indent=2))
            (tmp / "heatmap.png").write_bytes(plots.fig_to_png(plots.heatmap(err, rec.joint_names, rec.sequence_labels, "nominal model")))
            (tmp / "overlay_worst.png").write_bytes(plots.fig_to_png(plots.overlay(rec, sims, int(s), rec.joint_names[j])))
        print(f"wrote {out}/compare.json, heatmap.png, overlay_worst.png")
    return 0


def _cmd_diagnose(a) -> int:
    from adadex.sysid.diagnose import diagnose

    rec = _load_rec(a.recording, a.model)
    cands = tuple(a.candidates.split(",")) if a.candidates else EFFECT_NAMES
    for c in cands:
        if c not in EFFECT_NAMES:
            raise CliError(f"unknown candidate effect {c!r}; known: {', '.join(EFFECT_NAMES)}")
    _check_out(a, "diagnosis")
    d = diagnose(rec, base_patch=_load_patch(a.patch, a.model), candidates=cands,
                 joints=a.joints.split(",") if a.joints else None, nthread=a.threads)
    print("\n".join(d.findings))
    print(f"verdict: {d.verdict}  ({d.wall_time_s:.0f} s)")
    if a.out:
        with output_folder(a.out, "diagnosis", force=a.force, recognize=_RECOGNIZE["diagnosis"]) as tmp:
            d.save(tmp)
            plotted = _diagnosis_plot(d, tmp)
        print(f"wrote {Path(a.out) / 'diagnosis.json'}" + (f" and {Path(a.out) / 'hypotheses.png'}" if plotted else ""))
    return 0


def _diagnosis_plot(d, out: Path) -> bool:
    from adadex.sysid import plots

    hs = d.hypotheses[:12]
    if not hs:
        return False
    fig, ax = plots.plt.subplots(figsize=(7, 0.3 * len(hs) + 1))
    labels = [f"{h['effect']} @ {','.join(h['joints'])}" + (" (train only)" if h.get("scored_on") == "train" else "")
              for h in hs]
    ax.barh(range(len(hs)), [100 * (h["heldout_error_reduction"] if h["heldout_error_reduction"] is not None
                                    else h["train_error_reduction"]) for h in hs], color="tab:blue")
    ax.set_yticks(range(len(hs)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("held-out excess-error reduction (%)")
    ax.set_title(f"candidate effects (verdict: {d.verdict})", fontsize=9)
    (out / "hypotheses.png").write_bytes(plots.fig_to_png(fig))
    return True


def _parse_add(spec: str) -> tuple[str, list[str]]:
    if ":" not in spec:
        raise CliError(f"--add expects EFFECT:JOINT[,JOINT…], got {spec!r}")
    eff, joints = spec.split(":", 1)
    return eff, [j for j in joints.split(",") if j]


def _cmd_fit(a) -> int:
    from adadex.sysid.diagnose import Diagnosis
    from adadex.sysid.fit import fit_patch

    rec = _load_rec(a.recording, a.model)
    if bool(a.add) == bool(a.accept):
        raise CliError("give either --add EFFECT:JOINTS (repeatable) or --accept DIAGNOSIS_DIR")
    _check_out(a, "patch")
    if a.accept:
        diag = Diagnosis.load(a.accept)
        robot = _robot(a.model)
        if not same_model(diag.model, robot.model_id if robot else None):
            raise CliError(f"{a.accept}: the diagnosis was made on model {diag.model}, not "
                           f"{robot.model_id if robot else 'builtin'}; pass the same --model")
        patch = diag.patch(robot)
        if not len(patch):
            # nothing missing (or nothing found): the result is the starting patch, unchanged
            base = _load_patch(a.patch, a.model)
            with output_file(a.out, "patch", force=a.force):
                base.save(a.out)
            print(f"{a.accept}: nothing to add (verdict {diag.verdict}, no effect selected); wrote {a.out} "
                  f"with {'the effects of ' + str(a.patch) if a.patch else 'no effects'}")
            return 0
    else:
        patch = fit_patch(rec, [_parse_add(s) for s in a.add], base_patch=_load_patch(a.patch, a.model),
                          nthread=a.threads)
    patch = _load_patch(a.patch, a.model) + patch if a.patch and a.accept else patch
    with output_file(a.out, "patch", force=a.force):
        patch.save(a.out)
    print(f"wrote {a.out}: {patch.describe()}")
    _print_stages(rec, patch, a.threads)
    return 0


def _cmd_report(a) -> int:
    from adadex.sysid.diagnose import Diagnosis
    from adadex.sysid.report import write_report

    rec = _load_rec(a.recording, a.model)
    d = Diagnosis.load(a.diagnosis) if a.diagnosis else None
    _check_out(a, "report")
    pd = None
    if a.pd:
        from adadex.progress import progress_bar

        from adadex.sysid.fit import identify_pd, sequences_moving
        from adadex.sysid.replay import Replayer

        rep = Replayer(rec, nthread=a.threads)
        pd = [identify_pd(rep, j, sequences_moving(rec, j), method=m)
              for j in progress_bar(rec.joint_names, desc="kp/kd fits", unit="joint") for m in ("cma", "lsq")]
    with output_file(a.out, "report", force=a.force):
        path = write_report(rec, _load_patch(a.patch, a.model), a.out, diagnosis=d, nthread=a.threads, pd_results=pd)
    print(f"wrote {path}")
    return 0


def _cmd_demo(a) -> int:
    from adadex.sysid.demo import run_demo

    run_demo(recording=a.recording or DEMO_RECORDING, out=a.out, nthread=a.threads, model=a.model, force=a.force)
    return 0


def add_arguments(p) -> None:
    """Fill the ``adadex sysid`` parser ``p`` (made by :func:`adadex.cli.build_parser`) with its
    subcommands."""
    p.description, p.formatter_class = __doc__, argparse.RawDescriptionHelpFormatter
    s = p.add_subparsers(dest="sysid_command", required=True)

    def common(q):
        q.add_argument("--threads", type=int, default=2, help="rollout threads (default 2)")
        q.add_argument("--force", action="store_true", help="replace --out even if it is not an earlier output "
                       "of this command")
        add_model(q)

    def add_model(q):
        q.add_argument("--model", metavar="MJCF", help="replay on this MJCF (its position-servoed joints, by "
                                                       "name, its own options) instead of the built-in scene")

    q = s.add_parser("excite", help="design per-joint excitation (sine sweeps, chirp, multisine)")
    q.add_argument("--joints", required=True, help="comma-separated joint names")
    q.add_argument("--freqs", default="0.5,1.5,3", help="sine frequencies, Hz")
    q.add_argument("--amps", default="0.25,1", help="amplitudes as fractions of the in-limit range")
    q.add_argument("--poses", default="loaded,unloaded")
    q.add_argument("--kinds", default="sine,chirp,multisine")
    q.add_argument("--duration", type=float, default=3.0)
    q.add_argument("--rate", type=float, default=60.0, help="sample rate, Hz")
    q.add_argument("--out", required=True, help="plan.npz, or plan.csv for a folder of CSV files")
    q.add_argument("--force", action="store_true", help="replace --out even if it is not an earlier output "
                   "of this command")
    add_model(q)
    q.set_defaults(func=_cmd_excite)

    q = s.add_parser("simulate", help="make a recording from a plan with the model plus effects")
    q.add_argument("plan")
    q.add_argument("--patch", help="truth patch (JSON) with the effects to hide in the data")
    q.add_argument("--noise", type=float, default=2e-4, help="sensor noise std, rad")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--out", required=True)
    common(q)
    q.set_defaults(func=_cmd_simulate)

    q = s.add_parser("compare", help="replay on the model: errors and where it fails")
    q.add_argument("recording")
    q.add_argument("--patch", help="also show baseline → +each effect of this patch")
    q.add_argument("--out", help="folder for compare.json and plots")
    common(q)
    q.set_defaults(func=_cmd_compare)

    q = s.add_parser("diagnose", help="which physical effect is missing")
    q.add_argument("recording")
    q.add_argument("--out", help="folder for diagnosis.json and plots")
    q.add_argument("--patch", help="start from this patch instead of the nominal model")
    q.add_argument("--candidates", help=f"comma-separated subset of: {', '.join(EFFECT_NAMES)}")
    q.add_argument("--joints", help="diagnose these joints instead of the failing ones")
    common(q)
    q.set_defaults(func=_cmd_diagnose)

    q = s.add_parser("fit", help="fit chosen effects (or accept a diagnosis) into a model patch")
    q.add_argument("recording")
    q.add_argument("--add", action="append", default=[], metavar="EFFECT:JOINTS")
    q.add_argument("--accept", metavar="DIAGNOSIS_DIR", help="the effects a diagnosis selected (none selected: "
                   "'nothing to add', --out gets the starting patch unchanged)")
    q.add_argument("--patch", help="start from this patch")
    q.add_argument("--out", required=True)
    common(q)
    q.set_defaults(func=_cmd_fit)

    q = s.add_parser("report", help="self-contained HTML report: the error falling, plots, findings")
    q.add_argument("recording")
    q.add_argument("--patch")
    q.add_argument("--diagnosis")
    q.add_argument("--pd", action="store_true",
                   help="add the paper's per-joint kp/kd identification, CMA-ES vs least squares")
    q.add_argument("--out", required=True)
    common(q)
    q.set_defaults(func=_cmd_report)

    q = s.add_parser("demo", help="the whole loop on the shipped demo recording")
    q.add_argument("--recording", default=str(DEMO_RECORDING))
    q.add_argument("--out", default="adadex_demo", help="output folder (diagnosis/, patch.json, report.html), "
                   "written as one unit")
    common(q)
    q.set_defaults(func=_cmd_demo)


def run(args) -> int:
    """Run a sysid subcommand. Errors are reported by :func:`adadex.cli.main` through the one contract
    (:func:`adadex.errors.report_error`): bad input one line and exit code 2, a bug exit code 1."""
    return args.func(args)
