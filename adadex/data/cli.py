"""``adadex data …``: build, inspect and import reference datasets.

    adadex data build  --preset tiny|small|paper --out DIR [--seed N] [--clean] [--contact] [--planned-grasp] [--limit N] [--force]
    adadex data info   DIR                      counts per verb, object, split; rejection reasons
    adadex data show   DIR --index I --out ref.png [--no-render]
    adadex data import FILE.npz [FILE.npz …] --object NAME --out DIR [--contact] [--force]

``--out DIR`` replaces an existing dataset there, as one unit once the new one is complete; a
folder of other files or a file at DIR is refused unless ``--force``.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

from adadex.errors import check_number


def _cmd_build(a) -> int:
    from adadex.data.build import PRESETS, build_dataset
    from adadex.data.object_contact import ObjectContact
    from adadex.data.synth import NoiseConfig

    if a.limit is not None:             # before any work: 0 or -1 would build nothing, or all but one
        check_number("--limit", a.limit, low=1, integer=True)
    p = PRESETS[a.preset]
    n = min(a.limit, p.base_instructions) if a.limit else p.base_instructions
    print(f"building preset {p.name!r}: {n} base instructions × {p.paraphrases} paraphrases on "
          f"{len(p.objects)} objects (seed {a.seed}) → {a.out}")
    report = build_dataset(a.preset, a.out, seed=a.seed, noise=NoiseConfig.clean() if a.clean else NoiseConfig(),
                           limit=a.limit, progress=not a.quiet, force=a.force,
                           contact=ObjectContact() if a.contact else None, planned_grasp=a.planned_grasp)
    print(report.summary())
    print(f"wrote {report.path}; see `adadex data info {report.path}`")
    return 0


def _cmd_info(a) -> int:
    from adadex.data.reference import ReferenceDataset, check_frames

    check_number("--head", a.head, integer=True)
    ds = ReferenceDataset(a.dir)
    # The frames too, not only the index: a summary of a dataset with missing, truncated or damaged
    # frames would say it is fine (the first problem is named: file, or reference and frame).
    for start in range(0, len(ds), 256):        # in chunks: a large dataset is not read into memory at once
        check_frames(ds, range(start, min(start + 256, len(ds))))
    verbs = Counter(e["meta"].get("verb", "?") for e in ds.entries)
    objects = Counter(e["object"] for e in ds.entries)
    summary = {
        "path": str(ds.path), "references": len(ds), "frames": ds.num_frames,
        "groups": len({e["group"] for e in ds.entries}), "objects": len(objects), "verbs": dict(verbs),
        "splits": {name: {part: len(idx) for part, idx in parts.items()} for name, parts in ds.splits.items()},
        "rejected": ds.info.get("report", {}).get("rejected", {}),
        "arm_speed": arm_speed(ds),
        "approach_overlap": approach_overlap(ds),
    }
    if a.json:
        print(json.dumps(summary, indent=1))
        return 0
    print(f"{ds.path}: {len(ds)} references, {ds.num_frames} frames, {summary['groups']} semantic groups, "
          f"{len(objects)} objects")
    print("verbs:   " + ", ".join(f"{k} {v}" for k, v in sorted(verbs.items())))
    for name, parts in summary["splits"].items():
        print(f"split {name}: " + ", ".join(f"{k} {v}" for k, v in parts.items()))
    if summary["rejected"]:
        print("rejected while building: " + ", ".join(f"{k} {v}" for k, v in sorted(summary["rejected"].items())))
    speed = summary["arm_speed"]
    if speed["windows"]:
        print(f"arm joints faster than the env's servo targets ({speed['bound']:g} rad a frame) in {speed['faster']} of "
              f"{speed['windows']} episode windows; fastest {speed['fastest']:.2f} rad a frame ({speed['fastest_reference']})")
    inside = summary["approach_overlap"]
    if inside["windows"]:
        print(f"the hand reaches more than {1000 * inside['limit']:g} mm into the object before the grasp in "
              f"{inside['deeper']} of {inside['windows']} episode windows; deepest {1000 * inside['deepest']:.0f} mm "
              f"({inside['deepest_reference']})")
    for i, e in enumerate(ds.entries[: a.head]):
        print(f"  [{i}] {e['name']}: {e['instruction']!r} ({e['length']} frames, window from {e['window_start']})")
    return 0


def approach_overlap(ds, window: int | None = None, limit: float | None = None) -> dict:
    """How deep each reference's hand reaches into its object before it grasps it, kinematically (the
    reference's joints and object pose, :func:`~adadex.sim.grasp.object_overlap`), over its episode
    window (``window`` frames, default the tracking env's) up to the frame the fingers start to close
    (a planned grasp's ``close_from``, else the synthesis phase ``grasp``): ``{"limit", "windows",
    "deeper", "deepest", "deepest_reference"}`` with ``deeper`` the windows reaching more than ``limit``
    m in (default :data:`~adadex.data.planned_grasp.MAX_OVERLAP`). Replay of such a reference pins the
    object to the table, pushes or flings it before the grasp (docs/references.md)."""
    from adadex.data.planned_grasp import MAX_OVERLAP
    from adadex.data.reference import WINDOW_FRAMES, episode_references
    from adadex.sim.grasp import object_overlap
    from adadex.sim.scene import build_scene_model

    window = WINDOW_FRAMES if window is None else window
    limit = MAX_OVERLAP if limit is None else limit
    q, pose = ds.frames["hand_joint_pos"], ds.frames["object_pose"]
    depth, models = {}, {}
    for r in episode_references(ds, None, window):
        e = ds.entries[r]
        meta = e.get("meta", {})
        grasp = meta.get("planned_grasp", {}).get("close_from", meta.get("phases", {}).get("grasp"))
        if grasp is None or grasp <= e["window_start"]:
            continue
        if e["object"] not in models:
            models[e["object"]] = build_scene_model(e["object"])
        frames = slice(e["offset"] + e["window_start"], e["offset"] + min(grasp, e["window_start"] + window - 1) + 1)
        depth[e["name"]] = object_overlap(models[e["object"]], q[frames].numpy(), pose[frames].numpy()).depth
    deepest = max(depth, key=depth.get) if depth else None
    return {"limit": limit, "windows": len(depth), "deeper": sum(v > limit for v in depth.values()),
            "deepest": depth[deepest] if depth else None, "deepest_reference": deepest}


def arm_speed(ds, window: int | None = None, bound: float | None = None) -> dict:
    """How fast each reference's arm joints move within its episode window (``window`` frames, default
    :data:`~adadex.data.reference.WINDOW_FRAMES`, the tracking env's) against the most the env moves a
    servo target in a control step (``bound``, default :data:`~adadex.sim.scene.MAX_TARGET_STEP`):
    ``{"bound", "windows", "faster", "fastest", "fastest_reference"}`` — a reference faster than that
    is one the env, and so every policy, follows with a lag (docs/references.md: the planned grasp's
    approach)."""
    from adadex.data.reference import WINDOW_FRAMES, episode_references
    from adadex.sim.scene import MAX_TARGET_STEP

    window = WINDOW_FRAMES if window is None else window
    bound = MAX_TARGET_STEP if bound is None else bound
    q = ds.frames["hand_joint_pos"]
    steps = {}
    for r in episode_references(ds, None, window):
        e = ds.entries[r]
        start = e["offset"] + e["window_start"]
        arm = q[start: start + window, :6]
        steps[e["name"]] = float((arm[1:] - arm[:-1]).abs().max())
    fastest = max(steps, key=steps.get) if steps else None
    return {"bound": bound, "windows": len(steps), "faster": sum(v > bound for v in steps.values()),
            "fastest": steps[fastest] if steps else None, "fastest_reference": fastest}


def _cmd_show(a) -> int:
    from adadex.data.reference import ReferenceDataset
    from adadex.data.show import plot_reference

    ds = ReferenceDataset(a.dir)
    ref = ds[a.index]
    out = plot_reference(ref, a.out, render=False if a.no_render else None)
    print(f"wrote {out['path']}: {ref.instruction!r} on {ref.object_name} ({ref.num_frames} frames); "
          f"{out['render_note']}")
    return 0


def _cmd_import(a) -> int:
    from adadex.data.hoi_import import ImportRejected, import_npz
    from adadex.data.reference import DatasetError, is_dataset, save_dataset
    from adadex.data.object_contact import ObjectContact
    from adadex.data.retarget import Retargeter
    from adadex.io import check_output

    check_output(a.out, "dataset", force=a.force, recognize=is_dataset)   # before the slow part
    rt = Retargeter(contact=ObjectContact() if a.contact else None)
    refs, rejected = [], []
    for i, f in enumerate(a.files):
        try:
            refs.append(import_npz(f, object_name=a.object, instruction=a.instruction, group_id=i, retargeter=rt))
            print(f"imported {f}: {refs[-1].num_frames} frames")
        except ImportRejected as e:
            rejected.append({"file": str(f), **e.rejection.as_dict()})
            print(f"rejected {f}: {e.rejection.reason}: {e.rejection.detail}")
    if not refs:
        raise DatasetError(f"{a.out}: no file passed the feasibility filter; nothing written")
    path = save_dataset(refs, a.out, info={"imported": [str(f) for f in a.files], "rejections": rejected},
                        force=a.force)
    print(f"wrote {path}: {len(refs)} references ({len(rejected)} rejected)")
    return 0


def add_arguments(data) -> None:
    """Fill the ``adadex data`` parser ``data`` (made by :func:`adadex.cli.build_parser`) with its
    subcommands."""
    from adadex.data.presets import PRESETS

    data.description, data.formatter_class = __doc__, argparse.RawDescriptionHelpFormatter
    dsub = data.add_subparsers(dest="data_command", required=True)
    b = dsub.add_parser("build", help="synthesize, retarget, filter and split a reference dataset")
    b.add_argument("--preset", choices=sorted(PRESETS), default="tiny",
                   help="; ".join(f"{k}: {v.description}" for k, v in PRESETS.items()))
    b.add_argument("--out", required=True, help="dataset folder to write (an existing dataset is replaced atomically)")
    b.add_argument("--force", action="store_true", help="replace --out even if it is not a dataset")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--clean", action="store_true", help="no synthesis noise (for debugging)")
    b.add_argument("--contact", action="store_true",
                   help="object-aware retargeting: hand kept out of the object, fingertips pressed on it "
                        "(adadex.data.object_contact; many times slower to build: see the README)")
    b.add_argument("--planned-grasp", action="store_true",
                   help="hold the object with a pinch planned for this hand instead of the human's retargeted "
                        "grasp (adadex.data.planned_grasp)")
    b.add_argument("--limit", type=int, default=None, help="use only the first N base instructions")
    b.add_argument("--quiet", action="store_true", help="no progress bars")
    b.set_defaults(func=_cmd_build)
    i = dsub.add_parser("info", help="summary of a dataset")
    i.add_argument("dir")
    i.add_argument("--json", action="store_true")
    i.add_argument("--head", type=int, default=5, help="list the first N references (default 5)")
    i.set_defaults(func=_cmd_info)
    s = dsub.add_parser("show", help="plot one reference (3-D and top-down paths, rendered frames)")
    s.add_argument("dir")
    s.add_argument("--index", type=int, default=0)
    s.add_argument("--out", default="ref.png")
    s.add_argument("--no-render", action="store_true", help="skip the rendered frames")
    s.set_defaults(func=_cmd_show)
    m = dsub.add_parser("import", help="retarget human keypoint + object pose .npz files into a dataset")
    m.add_argument("files", nargs="+", type=Path)
    m.add_argument("--object", default=None, help="object name (if the files do not say)")
    m.add_argument("--instruction", default=None)
    m.add_argument("--out", required=True, help="dataset folder to write (an existing dataset is replaced atomically)")
    m.add_argument("--force", action="store_true", help="replace --out even if it is not a dataset")
    m.add_argument("--contact", action="store_true", help="object-aware retargeting (see `data build --contact`)")
    m.set_defaults(func=_cmd_import)


def run(args) -> int:
    """Run a data subcommand. Errors are reported by :func:`adadex.cli.main` through the one contract
    (:func:`adadex.errors.report_error`): bad input one line and exit code 2, a bug exit code 1."""
    return args.func(args)
