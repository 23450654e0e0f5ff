"""Hidden-effect recordings made as a user would make them, outside adadex's effect library: the
built-in world exported as MJCF and edited with ``MjSpec`` (a mass hung on a link, friction loss on
a joint), replayed after a 2 s pre-roll at rest, with sensor noise, every one of the robot's 22 joints
measured while a few are excited (the others hold the pose and fail only as knock-ons).

The diagnosis never sees the edit: it replays on the built-in model and must name the effect."""

from __future__ import annotations

import tempfile
from pathlib import Path

import mujoco
import numpy as np

from adadex.sim.model_source import ModelSource, _full_precision, export_world
from adadex.sim.robot import JOINT_NAMES
from adadex.sysid.excite import ExcitationPlan, design_excitation
from adadex.sysid.replay import Replayer

_WORLD: dict[str, Path] = {}


def _world() -> Path:
    if "path" not in _WORLD:
        _WORLD["path"] = export_world(Path(tempfile.mkdtemp(prefix="adadex_hidden_")) / "world.xml")
    return _WORLD["path"]


def edited_model(edit, name: str) -> ModelSource:
    """The exported built-in world with ``edit(spec)`` applied, as a model file of its own."""
    spec = mujoco.MjSpec.from_file(str(_world()))
    edit(spec)
    path = _world().parent / f"{name}.xml"
    path.write_text(_full_precision(spec.to_xml(), spec.compile()))   # MuJoCo writes 6 digits
    return ModelSource(path)


def hang_mass(body: str, mass: float, pos=(0.0, 0.0, 0.0)):
    """An edit: a small sphere of ``mass`` kg welded to ``body`` at ``pos`` (in the body's frame)."""
    def edit(spec):
        b = spec.body(body).add_body(name=f"hidden_payload_{body}", pos=list(pos))
        b.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.015, 0, 0], mass=mass, contype=0, conaffinity=0)
    return edit


def frictionloss(joint: str, value: float):
    """An edit: Coulomb friction (MuJoCo ``frictionloss``, N·m) on ``joint``."""
    def edit(spec):
        spec.joint(joint).frictionloss = value
    return edit


def recording(model: ModelSource, excited, *, freqs=(0.5, 2.0), amps=(0.3, 1.0), poses=("loaded", "unloaded"),
              kinds=("sine", "chirp"), duration=2.0, noise=2e-4, seed=0, measured=JOINT_NAMES, nthread=2):
    """A recording of the ``measured`` joints (default all 22) in which ``excited`` move one at a time,
    simulated on ``model`` after a 2 s pre-roll at rest, with N(0, ``noise``²) sensor noise."""
    plan = design_excitation(excited, freqs=freqs, amps=amps, poses=poses, kinds=kinds, duration=duration)
    measured = list(measured)
    cmd = np.repeat(plan.initial_qpos[:, None, :], len(plan.time), axis=1)
    idx = [JOINT_NAMES.index(j) for j in excited]
    cmd[:, :, idx] = plan.command
    full = ExcitationPlan(time=plan.time, joint_names=tuple(measured),
                          command=cmd[:, :, [JOINT_NAMES.index(j) for j in measured]],
                          initial_qpos=plan.initial_qpos, sequences=plan.sequences)
    proto = full.to_recording(full.command.copy())
    q = Replayer(proto, model=model, preroll_s=2.0, nthread=nthread).simulate()
    q = q + np.random.default_rng(seed).normal(0.0, noise, size=q.shape)
    return full.to_recording(q, {"noise_rad": noise, "seed": seed})


def soft_servos(joints, scale: float):
    """An edit: the position servos of ``joints`` with their stiffness (kp: gain and position bias) × ``scale``."""
    def edit(spec):
        for a in spec.actuators:
            if a.target in joints:
                a.gainprm[0] *= scale
                a.biasprm[1] *= scale
    return edit


def both(*edits):
    """An edit made of several."""
    def edit(spec):
        for e in edits:
            e(spec)
    return edit


def heavier_links(bodies, scale: float):
    """An edit: the mass and inertia of each of ``bodies`` × ``scale`` (what the model leaves out of them)."""
    def edit(spec):
        for name in bodies:
            b = spec.body(name)
            b.mass *= scale
            b.fullinertia = [v * scale for v in b.fullinertia]
    return edit
