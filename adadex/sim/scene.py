"""The tabletop scene: table, the arm + hand on it, one registry object on a free joint.

Timing
------
The paper runs physics at 60 Hz and control at 12 Hz. adadex keeps control at
:data:`CONTROL_HZ` = 12 Hz and uses :data:`PHYSICS_TIMESTEP` = 1/120 s (10 substeps per control
step): the largest step ≤ 1/60 s at which every soundness test passes (objects settle without
penetrating more than 2 mm, every joint servo settles, the scripted grasp lifts and holds a cube).
At 1/60 s the 5 cm cube slips out of the grasp within a second because contacts have to be made
softer than the fingertips can squeeze through (see ``benchmarks/timestep_sweep.py``).

qpos layout: the 22 robot joints in :data:`adadex.sim.robot.JOINT_NAMES` order, then the object's
free joint (position 3, quaternion 4, w first). qvel: 22 joint velocities, then 6 for the object.

Example
-------
>>> from adadex.sim.scene import build_scene_model
>>> model = build_scene_model("box_00")
>>> model.nq
29
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from adadex.sim import objects
from adadex.sim.robot import (
    HOME_QPOS,
    NUM_JOINTS,
    WORLD_GEOM_CONAFFINITY,
    WORLD_GEOM_CONTYPE,
    build_robot_spec,
)

#: Policy steps per second.
CONTROL_HZ = 12.0
#: The most a servo target moves in one control step, rad: the tracking env's action bound
#: (``TrackingConfig.max_action``'s default), what a reference can ask of the arm and be followed.
MAX_TARGET_STEP = 0.1
#: MuJoCo's timestep, s.
PHYSICS_TIMESTEP = 1.0 / 120.0
#: Physics steps per control step.
SUBSTEPS = int(round(1.0 / (CONTROL_HZ * PHYSICS_TIMESTEP)))

TABLE_HALF_SIZE = (0.45, 0.6, 0.02)  # m
TABLE_CENTER = (0.45, 0.0)           # the robot base sits at the origin, on the table's back half
OBJECT_HOME_XY = (0.45, 0.0)
FLOOR_Z = -0.75         # where objects rest by default, in front of the robot

OBJECT_BODY = "object"
OBJECT_QPOS = slice(NUM_JOINTS, NUM_JOINTS + 7)
OBJECT_QVEL = slice(NUM_JOINTS, NUM_JOINTS + 6)
#: gap between the table and an object resting in the ``home`` keyframe (m)
REST_GAP = 1e-3

# Contacts: elliptic cones with a high impratio make friction "hard" so grasps do not creep; the
# solref time constant is 2·dt, the stiffest MuJoCo allows at a given step.
CONTACT_SOLIMP = (0.95, 0.99, 0.001, 0.5, 2.0)


@dataclass(frozen=True)
class PhysicsOptions:
    """Solver settings shared by every scene; change them in one place.

    :func:`apply_physics_options` sets them on a spec; the contacts' ``solref`` time constant is
    twice ``timestep``.

    Attributes:
        timestep: physics step, s (default :data:`PHYSICS_TIMESTEP`, 1/120 s).
        integrator: MuJoCo ``mjtIntegrator`` value (default implicitfast).
        cone: MuJoCo friction cone, ``mjtCone`` value (default elliptic).
        impratio: ratio of frictional to normal constraint impedance (default 10).
        iterations: maximum main-solver iterations (default 50).
        ls_iterations: maximum line-search iterations (default 20).
        noslip_iterations: no-slip solver iterations (default 0: off).

    Examples:
        >>> PhysicsOptions().timestep == 1 / 120
        True
        >>> PhysicsOptions(iterations=100).iterations
        100
    """

    timestep: float = PHYSICS_TIMESTEP
    integrator: int = int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST)
    cone: int = int(mujoco.mjtCone.mjCONE_ELLIPTIC)
    impratio: float = 10.0
    iterations: int = 50
    ls_iterations: int = 20
    noslip_iterations: int = 0


def apply_physics_options(spec: mujoco.MjSpec, opts: PhysicsOptions = PhysicsOptions()) -> None:
    """Set ``opts`` (timestep, integrator, cone, solver iterations) on ``spec``, in place, and give every
    geom the contact ``solref`` (twice the timestep, critically damped) and :data:`CONTACT_SOLIMP`."""
    spec.option.timestep = opts.timestep
    spec.option.integrator = opts.integrator
    spec.option.cone = opts.cone
    spec.option.impratio = opts.impratio
    spec.option.iterations = opts.iterations
    spec.option.ls_iterations = opts.ls_iterations
    spec.option.noslip_iterations = opts.noslip_iterations
    solref = [2 * opts.timestep, 1.0]
    for g in spec.geoms:
        g.solref = solref
        g.solimp = list(CONTACT_SOLIMP)


def build_scene_spec(object_name: str | None = "box_00", *,
                     object_xy: tuple[float, float] = OBJECT_HOME_XY,
                     options: PhysicsOptions = PhysicsOptions(), uniform_layout: bool = False,
                     object_scale: float = 1.0) -> mujoco.MjSpec:
    """Robot + table + one object (or none with ``object_name=None``) as an ``MjSpec``.

    The object body is named :data:`OBJECT_BODY`; it rests on the table at ``object_xy``. With
    ``uniform_layout`` the object's geoms are padded to :data:`~adadex.sim.objects.MAX_OBJECT_PARTS`,
    so scenes of any two objects share one structure (``MjModel.signature``) and one
    ``BatchedSim`` can step worlds holding different objects in a single rollout call.
    ``object_scale`` scales the object uniformly (it still rests on the table).

    Args:
        object_name: the object (a name of :mod:`adadex.sim.objects`; default ``"box_00"``); None:
            robot and table only.
        object_xy: where the object rests on the table, world x, y in m (default
            :data:`OBJECT_HOME_XY`, (0.45, 0.0)).
        options: the solver settings (:class:`PhysicsOptions`).
        uniform_layout: pad the object's geoms to a shared layout (above).
        object_scale: uniform scale factor of the object (default 1.0).

    Returns:
        the uncompiled ``mujoco.MjSpec``, with a ``home`` keyframe (robot at its home pose, object
        at rest).
    """
    spec = build_robot_spec()
    spec.modelname = f"adadex_scene_{object_name or 'empty'}"
    spec.stat.center = [0.35, 0.0, 0.2]
    spec.stat.extent = 1.0
    spec.visual.global_.offwidth = 640
    spec.visual.global_.offheight = 480
    tx, ty = TABLE_CENTER
    hx, hy, hz = TABLE_HALF_SIZE
    spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx, hy, hz],
                            pos=[tx, ty, -hz], contype=WORLD_GEOM_CONTYPE,
                            conaffinity=WORLD_GEOM_CONAFFINITY, condim=4,
                            friction=[0.8, 0.01, 0.001], rgba=[0.55, 0.42, 0.3, 1])
    # A floor under the table, so that a dropped object comes to rest instead of falling forever.
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.1],
                            pos=[0, 0, FLOOR_Z], contype=WORLD_GEOM_CONTYPE,
                            conaffinity=WORLD_GEOM_CONAFFINITY, rgba=[0.3, 0.3, 0.32, 1])
    spec.worldbody.add_light(name="top", pos=[0.4, 0, 1.5], dir=[0, 0, -1])
    if object_name is not None:
        info = objects.get_object(object_name)
        body = spec.worldbody.add_body(name=OBJECT_BODY,
                                       pos=[object_xy[0], object_xy[1], object_scale * info.half_height + REST_GAP])
        body.add_freejoint(name="object_free")
        objects.add_object_geoms(spec, body, object_name,
                                 pad_to=objects.MAX_OBJECT_PARTS if uniform_layout else None, scale=object_scale)
    apply_physics_options(spec, options)
    key_qpos = list(HOME_QPOS)
    if object_name is not None:
        key_qpos += [object_xy[0], object_xy[1], object_scale * info.half_height + REST_GAP,
                     1.0, 0.0, 0.0, 0.0]
    spec.add_key(name="home", qpos=key_qpos, ctrl=list(HOME_QPOS))
    return spec


def build_scene_model(object_name: str | None = "box_00", **kwargs) -> mujoco.MjModel:
    """Compile :func:`build_scene_spec`.

    Args:
        object_name: the object on the table (default ``"box_00"``); None: no object.
        **kwargs: :func:`build_scene_spec`'s keyword arguments (``object_xy``, ``options``,
            ``uniform_layout``, ``object_scale``).

    Returns:
        the compiled ``mujoco.MjModel``.
    """
    return build_scene_spec(object_name, **kwargs).compile()


def home_state(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """``(qpos, ctrl)`` of the ``home`` keyframe of a scene model.

    Args:
        model: a scene model built by :func:`build_scene_spec` (it has a ``home`` key).

    Returns:
        copies of the keyframe's ``qpos`` and ``ctrl``.
    """
    key = model.key("home")
    return key.qpos.copy(), key.ctrl.copy()


def resting_height(model: mujoco.MjModel) -> float:
    """Height of the object's origin above the table top when it rests upright in ``model`` (at the
    size it was compiled with), read from the ``home`` keyframe: no mesh is built for it."""
    return float(model.key("home").qpos[OBJECT_QPOS][2]) - REST_GAP


def descends(model: mujoco.MjModel, body: int, ancestor: int) -> bool:
    """Whether ``body`` is ``ancestor`` or below it in ``model``'s body tree."""
    while body > 0:
        if body == ancestor:
            return True
        body = int(model.body_parentid[body])
    return False
