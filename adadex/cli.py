"""The ``adadex`` command.

``adadex sim info [--json]``   the robot, timing and object registry
``adadex sim export [--out P]`` write the nominal world (robot + table + options) as MJCF (an existing P
                               only if an earlier export, or with --force)
``adadex data …``              reference datasets: build, info, show, import
``adadex sysid …``             model vs measurement: excite, simulate, compare, diagnose, fit, report, demo
``adadex encoder …``           point-cloud encoder (object latent): train, eval
``adadex demo``                a short simulation demo (settle objects, grasp and lift a cube)

Errors in what you give (a missing or bad file, a bad value, an --out that holds something else)
are one line on stderr and exit code 2; anything else is a bug in adadex: one line and exit code 1.
``adadex --debug …`` shows the full traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys

#: The subcommands defined in their own modules: name → (module, one-line help). Each module's
#: ``add_arguments(parser)`` fills the subcommand's parser when that subcommand is used (parsed, or its
#: help shown), so ``adadex --help`` and the other subcommands import none of torch, TorchRL or MuJoCo.
SUBCOMMANDS = {
    "data": ("adadex.data.cli", "hand–object reference datasets: build, info, show, import"),
    "sysid": ("adadex.sysid.cli", "model vs measurement: compare, diagnose, fit, report"),
    "encoder": ("adadex.train.encoder_cli", "point-cloud encoder (object latent): train, eval"),
}


class LazyParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose arguments are added by ``populate(parser)`` the first
    time it parses or formats its help or usage (the subcommands' parsers: see :data:`SUBCOMMANDS`).

    Args:
        populate: called once with the parser before its first use; None for an ordinary parser.
        *args, **kwargs: as for :class:`argparse.ArgumentParser`.
    """

    def __init__(self, *args, populate=None, **kwargs):
        super().__init__(*args, **kwargs)
        self._populate = populate

    def populate(self) -> LazyParser:
        """Add the arguments now (idempotent); return the parser."""
        populate, self._populate = self._populate, None
        if populate is not None:
            populate(self)
        return self

    def parse_known_args(self, args=None, namespace=None):
        self.populate()
        return super().parse_known_args(args, namespace)

    def format_usage(self):
        self.populate()
        return super().format_usage()

    def format_help(self):
        self.populate()
        return super().format_help()


def _sim_info() -> dict:
    from adadex.sim import objects
    from adadex.sim.robot import (
        GAINS,
        JOINT_NAMES,
        TRACKED_SITES,
        effort_limits,
        joint_group,
        joint_limits,
    )
    from adadex.sim.scene import CONTROL_HZ, PHYSICS_TIMESTEP, SUBSTEPS

    lim, eff = joint_limits(), effort_limits()
    return {
        "joints": [
            {"name": n, "group": joint_group(n), "range": [float(lim[i, 0]), float(lim[i, 1])],
             "effort_limit": float(eff[i]), "kp": GAINS[joint_group(n)].kp, "kv": GAINS[joint_group(n)].kv,
             "armature": GAINS[joint_group(n)].armature}
            for i, n in enumerate(JOINT_NAMES)
        ],
        "joint_names": list(JOINT_NAMES),
        "tracked_links": list(TRACKED_SITES),
        "physics_timestep": PHYSICS_TIMESTEP,
        "physics_hz": 1.0 / PHYSICS_TIMESTEP,
        "control_hz": CONTROL_HZ,
        "substeps": SUBSTEPS,
        "objects": [
            {"name": o.name, "category": o.category, "split": objects.object_split(o.name),
             "mass_kg": round(o.mass, 4)}
            for o in objects.REGISTRY.values()
        ],
    }


def _print_info(info: dict) -> None:
    print(f"robot: {len(info['joint_names'])} joints, physics {info['physics_hz']:.0f} Hz, "
          f"control {info['control_hz']:.0f} Hz ({info['substeps']} substeps)")
    print(f"{'joint':<8} {'group':<13} {'range (rad)':<18} {'effort':>7} {'kp':>7} {'kv':>6}")
    for j in info["joints"]:
        lo, hi = j["range"]
        print(f"{j['name']:<8} {j['group']:<13} [{lo:+.3f}, {hi:+.3f}]  {j['effort_limit']:7.2f} "
              f"{j['kp']:7.1f} {j['kv']:6.2f}")
    print("tracked links:", ", ".join(info["tracked_links"]))
    cats: dict[str, list[str]] = {}
    for o in info["objects"]:
        cats.setdefault(o["category"], []).append(o["name"] + ("*" if o["split"] == "held_out" else ""))
    print(f"objects: {len(info['objects'])} in {len(cats)} categories (* = held out, unseen-object split)")
    for c, names in cats.items():
        print(f"  {c:<10} {' '.join(names)}")


def _cmd_sim_info(args) -> int:
    info = _sim_info()
    if args.json:
        json.dump(info, sys.stdout, indent=2)
        print()
    else:
        _print_info(info)
    return 0


#: The kind of output ``sim export --out`` writes (its marker: :func:`adadex.io.output_file`).
EXPORT_KIND = "sim export"


def _cmd_sim_export(args) -> int:
    from adadex.io import output_file
    from adadex.sim.model_source import export_world
    from adadex.sim.robot import ROBOT_MJCF, export_mjcf

    if args.out:                        # the user's path: replaced only if an earlier export, or --force
        with output_file(args.out, EXPORT_KIND, force=args.force):
            path = export_mjcf(args.out) if args.robot_only else export_world(args.out)
        print(path)
    elif args.robot_only:
        print(export_mjcf())
    else:
        print(export_mjcf())
        print(export_world(ROBOT_MJCF.with_name("world.xml")))
    return 0


def _cmd_demo(args) -> int:
    from adadex.sim.demo import run_demo

    run_demo(worlds=args.worlds, nthread=args.threads, seed=args.seed)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``adadex`` parser. The subcommands of :data:`SUBCOMMANDS` get their arguments when used
    (:class:`LazyParser`): building the parser imports no module of theirs."""
    p = LazyParser(prog="adadex", description=__doc__.split("\n\n")[0],
                   formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--debug", action="store_true", help="show the full traceback of any error")
    sub = p.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("sim", help="robot, scene and simulator")
    sim_sub = sim.add_subparsers(dest="sim_command", required=True)
    info = sim_sub.add_parser("info", help="joint names, limits, gains, tracked links, timing, objects")
    info.add_argument("--json", action="store_true", help="print JSON instead of a table")
    info.set_defaults(func=_cmd_sim_info)
    exp = sim_sub.add_parser(
        "export", help="write the nominal world MJCF (robot + table + physics options) for `--model`",
        description="Write the full nominal world (robot + table + physics options) to --out; `adadex sysid "
                    "... --model` on it replays exactly as the built-in scene. Without --out: assets/robot/"
                    "robot.xml (the robot alone, for kinematics tools) and assets/robot/world.xml.")
    exp.add_argument("--out", default=None, help="where to write the world (with --robot-only: the robot)")
    exp.add_argument("--robot-only", action="store_true", help="the robot alone, without table and options")
    exp.add_argument("--force", action="store_true", help="replace --out even if it is not an earlier "
                     "`adadex sim export` (an existing file is otherwise refused)")
    exp.set_defaults(func=_cmd_sim_export)

    for name, (module, help) in SUBCOMMANDS.items():
        sub.add_parser(name, help=help, populate=lambda parser, module=module:
                       importlib.import_module(module).add_arguments(parser))

    demo = sub.add_parser("demo", help="short simulation demo: objects settle, the hand grasps and lifts a cube")
    demo.add_argument("--worlds", type=int, default=16, help="worlds stepped together (default 16)")
    demo.add_argument("--threads", type=int, default=2, help="rollout threads (default 2)")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv``; return the exit code. The one place the ``adadex`` command turns
    an error into an exit code (:func:`adadex.errors.report_error`, for every subcommand alike): bad
    input is one line and 2, anything else a bug, one line and 1; ``--debug`` raises it instead."""
    args = build_parser().parse_args(argv)
    try:
        return _dispatch(args)
    except Exception as e:
        from adadex.errors import report_error

        if args.debug:
            raise
        return report_error(_prog(args), e, hint="; run `adadex --debug …` for the traceback")


def _prog(args) -> str:
    """The command as the user typed it, for messages: ``adadex sysid fit``, ``adadex sim export``."""
    sub = getattr(args, f"{args.command}_command", None)
    return f"adadex {args.command}" + (f" {sub}" if sub else "")


def _dispatch(args) -> int:
    if args.command == "sysid":
        from adadex.sysid.cli import run

        return run(args)
    if args.command == "data":
        from adadex.data.cli import run

        return run(args)
    if args.command == "encoder":
        from adadex.train.encoder_cli import run

        return run(args)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
