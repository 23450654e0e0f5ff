"""The arm + hand robot: a 6-DoF xArm6-like arm carrying a 16-DoF LEAP-like hand, built with MjSpec.

The robot is built in code (:func:`build_robot_spec`) so that every later piece — the scene, the
physical effects of the sysid workbench, domain randomization — edits one ``mujoco.MjSpec`` rather
than a file. :func:`export_mjcf` writes the same model to ``assets/robot/robot.xml`` for tools that
want a file (pytorch-kinematics, viewers); a test checks that the file and the builder agree.

Conventions
-----------
* :data:`JOINT_NAMES` is *the* 22-joint order used everywhere in adadex (observations, actions,
  references, recordings): ``arm_j1 … arm_j6`` then the LEAP order
  ``if_mcp if_rot if_pip if_dip mf_* rf_* th_cmc th_axl th_mcp th_ipl``.
* Actuators are position servos (PD) in the same order; ``ctrl`` is a joint-position target.
* :data:`TRACKED_SITES` are the 5 tracked links: palm, thumb tip, index tip, middle tip, ring tip.
* The hand's palm faces the flange frame's −x direction; fingers extend along the flange's +z.

Collision filtering: robot geoms have ``contype=2, conaffinity=1`` and the world (table, objects)
``contype=1, conaffinity=3``, so the robot touches the world but never itself (self-collision is a
feasibility check on references, done kinematically, not a force in the simulation).

Example
-------
>>> from adadex.sim.robot import build_robot_spec, JOINT_NAMES
>>> model = build_robot_spec().compile()
>>> model.nu == len(JOINT_NAMES) == 22
True
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from dataclasses import dataclass

import mujoco
import numpy as np

from adadex.errors import AdadexError
from adadex.resources import asset

ARM_JOINTS: tuple[str, ...] = tuple(f"arm_j{i}" for i in range(1, 7))
HAND_JOINTS: tuple[str, ...] = (
    "if_mcp", "if_rot", "if_pip", "if_dip",
    "mf_mcp", "mf_rot", "mf_pip", "mf_dip",
    "rf_mcp", "rf_rot", "rf_pip", "rf_dip",
    "th_cmc", "th_axl", "th_mcp", "th_ipl",
)
#: The one joint order used everywhere in adadex (22 joints).
JOINT_NAMES: tuple[str, ...] = ARM_JOINTS + HAND_JOINTS
#: Joints of the robot: 6 arm + 16 hand.
NUM_JOINTS = len(JOINT_NAMES)

#: Tracked links (sites), in the order of every ``link_pose[5, 7]`` array.
TRACKED_SITES: tuple[str, ...] = ("palm", "thumb_tip", "index_tip", "middle_tip", "ring_tip")

ROBOT_GEOM_CONTYPE, ROBOT_GEOM_CONAFFINITY = 2, 1
WORLD_GEOM_CONTYPE, WORLD_GEOM_CONAFFINITY = 1, 3

HALF_PI = math.pi / 2

# --------------------------------------------------------------------------------------------
# xArm6 kinematics and dynamics. Source: UFACTORY xarm_ros2, xarm_description/urdf/xarm6/
# xarm6.urdf.xacro (joint origins xyz/rpy, effort limits, link masses, inertial frames and
# inertia tensors) and xarm6_robot_macro.xacro with limited:=true (position limits).
# Every joint rotates about its local +z. rpy below is the URDF joint-origin roll (pitch = yaw = 0).
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ArmLink:
    """One arm link of the built robot: its joint origin, range, effort, inertia and collision capsule
    (units in the field comments)."""

    joint: str
    pos: tuple[float, float, float]          # joint origin in parent link frame, m
    roll: float                              # joint origin roll about parent x, rad
    range: tuple[float, float]               # rad
    effort: float                            # N·m
    mass: float                              # kg
    com: tuple[float, float, float]          # m, link frame
    inertia: tuple[float, float, float, float, float, float]   # ixx iyy izz ixy ixz iyz, kg·m²
    capsule: tuple[tuple[float, float, float], tuple[float, float, float], float]  # from, to, radius


_PI99 = math.pi * 0.99
ARM_LINKS: tuple[ArmLink, ...] = (
    ArmLink("arm_j1", (0, 0, 0.267), 0.0, (-_PI99, _PI99), 50.0, 2.16, (-0.002, 0.02692, -0.01332),
            (0.00539427, 0.0048979, 0.00311573, 1.095e-05, 1.635e-06, 0.000793),
            ((0, 0, -0.06), (0, 0, 0.03), 0.05)),
    ArmLink("arm_j2", (0, 0, 0), -HALF_PI, (-2.059, 2.0944), 50.0, 1.71, (0.03531, -0.21398, 0.03386),
            (0.0248674, 0.00485548, 0.02387827, -0.00430651, -0.00067797, 0.00457245),
            ((0, 0, 0), (0.0535, -0.2845, 0), 0.045)),
    ArmLink("arm_j3", (0.0535, -0.2845, 0), 0.0, (-_PI99, 0.19198), 32.0, 1.384, (0.06781, 0.10749, 0.01457),
            (0.0053694, 0.0032423, 0.00501731, 0.0014185, -0.00092094, -0.00169178),
            ((0, 0, 0), (0.0775, 0.22, 0), 0.04)),
    ArmLink("arm_j4", (0.0775, 0.3425, 0), -HALF_PI, (-_PI99, _PI99), 32.0, 1.115, (-0.00021, 0.02578, -0.02538),
            (0.00439263, 0.0040077, 0.00110321, 5.028e-05, 1.374e-05, 0.00045338),
            ((0, 0, -0.1), (0, 0, 0), 0.04)),
    ArmLink("arm_j5", (0, 0, 0), HALF_PI, (-1.69297, math.pi), 32.0, 1.275, (0.05428, 0.01781, 0.00543),
            (0.001202758, 0.0022876, 0.0026866, 0.000492428, -0.00039147, -0.0001235),
            ((0, 0, 0), (0.076, 0.06, 0), 0.037)),
    ArmLink("arm_j6", (0.076, 0.097, 0), -HALF_PI, (-_PI99, _PI99), 20.0, 0.1096, (0, 0.00064, -0.00952),
            (4.5293e-05, 4.8111e-05, 7.9715e-05, 0, 0, 0),
            ((0, 0, -0.02), (0, 0, 0.0), 0.035)),
)
ARM_BASE_MASS = 2.7  # kg, link_base (URDF)

# --------------------------------------------------------------------------------------------
# LEAP hand. Joint structure and ranges: MuJoCo Menagerie leap_hand/right_hand.xml (joint classes
# mcp/rot/pip/dip, thumb_cmc/axl/mcp/ipl). Link lengths approximate the LEAP hand's (MCP→PIP ≈ 64 mm
# through the two MCP motors, PIP→DIP 36 mm, DIP→tip 45 mm; fingers 45 mm apart); geometry here is
# primitives sized like the real links, not the CAD meshes.
# --------------------------------------------------------------------------------------------
FINGER_RANGES = {
    "mcp": (-0.314, 2.23), "rot": (-1.047, 1.047), "pip": (-0.506, 1.885), "dip": (-0.366, 2.042),
}
THUMB_RANGES = {
    "cmc": (-0.349, 2.094), "axl": (-0.349, 2.094), "mcp": (-0.47, 2.443), "ipl": (-1.34, 1.88),
}
HAND_EFFORT = 0.95  # N·m, stall torque of the LEAP hand's Dynamixel XC330-M288-T servos
FINGER_Y = {"if": 0.045, "mf": 0.0, "rf": -0.045}
FINGER_BASE_Z = 0.115            # flange → MCP axis along the tool axis, m
FINGER_SEGMENTS = (0.040, 0.024, 0.036, 0.045)  # mcp→rot, rot→pip, pip→dip, dip→tip, m
FINGER_RADIUS = 0.0095
TIP_FRICTION = (1.2, 0.02, 0.002)  # sliding, torsional, rolling: rubber-like tips for grasping
LINK_FRICTION = (0.9, 0.01, 0.001)


@dataclass(frozen=True)
class ServoGains:
    """Position-servo gains of one joint group: kp in N·m/rad, kv in N·m·s/rad, armature in kg·m²."""

    kp: float
    kv: float
    armature: float
    damping: float
    frictionloss: float


#: PD gains per joint group. The arm's armature is the reflected rotor inertia of a harmonic drive
#: (order 0.1–0.3 kg·m² at 100:1); the hand's is the XC330's rotor through its 288:1 gearbox
#: (≈ 2e-3 kg·m²). Armature is physical here and is also what keeps the servos stable at the coarse
#: physics step. kv gives roughly critical damping of the servo with the link's inertia.
GAINS: dict[str, ServoGains] = {
    "arm_shoulder": ServoGains(kp=1500.0, kv=120.0, armature=0.25, damping=1.0, frictionloss=0.2),  # j1–j3
    "arm_wrist": ServoGains(kp=400.0, kv=25.0, armature=0.08, damping=0.5, frictionloss=0.1),      # j4–j6
    "finger": ServoGains(kp=6.0, kv=0.25, armature=0.003, damping=0.03, frictionloss=0.001),
    "thumb": ServoGains(kp=6.0, kv=0.25, armature=0.003, damping=0.03, frictionloss=0.001),
}


def joint_group(name: str) -> str:
    """The gain group of a joint: ``arm_shoulder``, ``arm_wrist``, ``finger`` or ``thumb``."""
    if name in ARM_JOINTS:
        return "arm_shoulder" if ARM_JOINTS.index(name) < 3 else "arm_wrist"
    if name.startswith("th_"):
        return "thumb"
    if name in HAND_JOINTS:
        return "finger"
    raise UnknownJointError(name)


class UnknownJointError(AdadexError, KeyError):
    """A joint name that is not one of :data:`JOINT_NAMES`."""

    def __init__(self, name: str, known=None, model: str | None = None):
        import difflib

        known = JOINT_NAMES if known is None else tuple(known)
        close = difflib.get_close_matches(str(name), known, n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        whose = "adadex joints" if model is None else f"the servoed joints of {model}"
        super().__init__(f"unknown joint {name!r}: {whose} are {', '.join(known)}{hint}")

    @classmethod
    def for_model(cls, name: str, known, model: str) -> "UnknownJointError":
        """The error for a joint that is not among the servoed joints of a user's model."""
        return cls(name, known, model)


def joint_index(names) -> np.ndarray:
    """Indices into :data:`JOINT_NAMES` for a list of joint names; raises :class:`UnknownJointError`."""
    out = []
    for n in names:
        if n not in JOINT_NAMES:
            raise UnknownJointError(n)
        out.append(JOINT_NAMES.index(n))
    return np.asarray(out, dtype=np.int64)


def _quat_x(angle: float) -> list[float]:
    return [math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0]


def _add_joint_and_actuator(spec: mujoco.MjSpec, body: mujoco.MjsBody, name: str,
                            axis, rng: tuple[float, float], effort: float) -> None:
    g = GAINS[joint_group(name)]
    body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=list(axis), range=list(rng),
                   limited=mujoco.mjtLimited.mjLIMITED_TRUE, armature=g.armature, damping=g.damping,
                   frictionloss=g.frictionloss, actfrcrange=[-effort, effort],
                   actfrclimited=mujoco.mjtLimited.mjLIMITED_TRUE)
    act = spec.add_actuator(name=f"{name}_pos", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
    act.set_to_position(kp=g.kp, kv=g.kv)
    act.ctrlrange = list(rng)
    act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    act.forcerange = [-effort, effort]
    act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE


def _robot_geom(body: mujoco.MjsBody, name: str, gtype, size, *, fromto=None, pos=None,
                friction=LINK_FRICTION, rgba=(0.85, 0.85, 0.88, 1.0), mass_from_density=False):
    kw = dict(name=name, type=gtype, size=list(size) + [0.0] * (3 - len(size)),
              contype=ROBOT_GEOM_CONTYPE, conaffinity=ROBOT_GEOM_CONAFFINITY, condim=4,
              friction=list(friction), rgba=list(rgba))
    if fromto is not None:
        kw["fromto"] = list(fromto)
    if pos is not None:
        kw["pos"] = list(pos)
    g = body.add_geom(**kw)
    if not mass_from_density:
        g.density = 0.0
    return g


def _build_arm(spec: mujoco.MjSpec, base: mujoco.MjsBody) -> mujoco.MjsBody:
    _robot_geom(base, "base_link", mujoco.mjtGeom.mjGEOM_CYLINDER, (0.06, 0.09), pos=(0, 0, 0.09),
                rgba=(0.9, 0.9, 0.92, 1))
    parent = base
    for i, link in enumerate(ARM_LINKS, start=1):
        body = parent.add_body(name=f"link{i}", pos=list(link.pos), quat=_quat_x(link.roll))
        body.explicitinertial = True
        body.mass = link.mass
        body.ipos = list(link.com)
        body.fullinertia = list(link.inertia)
        _add_joint_and_actuator(spec, body, link.joint, (0, 0, 1), link.range, link.effort)
        a, b, r = link.capsule
        _robot_geom(body, f"link{i}_col", mujoco.mjtGeom.mjGEOM_CAPSULE, (r,), fromto=(*a, *b))
        parent = body
    return parent


def _finger(spec: mujoco.MjSpec, palm: mujoco.MjsBody, prefix: str, y: float, site: str) -> None:
    """Index/middle/ring finger: MCP flexion, MCP rotation (ab/adduction), PIP, DIP."""
    flex_axis = (0, -1, 0)  # positive flexion curls the finger toward the palm side (−x)
    l_mr, l_rp, l_pd, l_dt = FINGER_SEGMENTS
    r = FINGER_RADIUS
    bs = palm.add_body(name=f"{prefix}_bs", pos=[0, y, FINGER_BASE_Z])
    _add_joint_and_actuator(spec, bs, f"{prefix}_mcp", flex_axis, FINGER_RANGES["mcp"], HAND_EFFORT)
    _robot_geom(bs, f"{prefix}_bs_col", mujoco.mjtGeom.mjGEOM_BOX, (0.012, 0.012, l_mr / 2),
                pos=(0, 0, l_mr / 2), mass_from_density=True).density = 1300
    px = bs.add_body(name=f"{prefix}_px", pos=[0, 0, l_mr])
    _add_joint_and_actuator(spec, px, f"{prefix}_rot", (1, 0, 0), FINGER_RANGES["rot"], HAND_EFFORT)
    _robot_geom(px, f"{prefix}_px_col", mujoco.mjtGeom.mjGEOM_CAPSULE, (r,),
                fromto=(0, 0, 0.004, 0, 0, l_rp), mass_from_density=True).density = 1300
    md = px.add_body(name=f"{prefix}_md", pos=[0, 0, l_rp])
    _add_joint_and_actuator(spec, md, f"{prefix}_pip", flex_axis, FINGER_RANGES["pip"], HAND_EFFORT)
    _robot_geom(md, f"{prefix}_md_col", mujoco.mjtGeom.mjGEOM_CAPSULE, (r,),
                fromto=(0, 0, 0.004, 0, 0, l_pd), mass_from_density=True).density = 1300
    ds = md.add_body(name=f"{prefix}_ds", pos=[0, 0, l_pd])
    _add_joint_and_actuator(spec, ds, f"{prefix}_dip", flex_axis, FINGER_RANGES["dip"], HAND_EFFORT)
    _robot_geom(ds, f"{prefix}_ds_col", mujoco.mjtGeom.mjGEOM_CAPSULE, (r,),
                fromto=(0, 0, 0.004, 0, 0, l_dt - r), mass_from_density=True).density = 1300
    _robot_geom(ds, f"{prefix}_tip_col", mujoco.mjtGeom.mjGEOM_SPHERE, (r * 1.05,),
                pos=(-0.002, 0, l_dt - r), friction=TIP_FRICTION, rgba=(0.95, 0.95, 0.95, 1))
    ds.add_site(name=site, pos=[-0.002, 0, l_dt - r], size=[0.004, 0, 0])


def _thumb(spec: mujoco.MjSpec, palm: mujoco.MjsBody) -> None:
    """Thumb: CMC swings it out of the palm plane, AXL raises it toward the fingers, MCP/IPL curl."""
    r = FINGER_RADIUS
    bs = palm.add_body(name="th_bs", pos=[-0.025, 0.055, 0.045])
    _add_joint_and_actuator(spec, bs, "th_cmc", (0, 0, 1), THUMB_RANGES["cmc"], HAND_EFFORT)
    _robot_geom(bs, "th_bs_col", mujoco.mjtGeom.mjGEOM_BOX, (0.011, 0.012, 0.011), pos=(0, 0.008, 0),
                mass_from_density=True).density = 1300
    mp = bs.add_body(name="th_mp", pos=[0, 0.02, 0])
    _add_joint_and_actuator(spec, mp, "th_axl", (1, 0, 0), THUMB_RANGES["axl"], HAND_EFFORT)
    _robot_geom(mp, "th_mp_col", mujoco.mjtGeom.mjGEOM_CAPSULE, (r,), fromto=(0, 0.004, 0, 0, 0.045, 0),
                mass_from_density=True).density = 1300
    px = mp.add_body(name="th_px", pos=[0, 0.045, 0])
    _add_joint_and_actuator(spec, px, "th_mcp", (1, 0, 0), THUMB_RANGES["mcp"], HAND_EFFORT)
    _robot_geom(px, "th_px_col", mujoco.mjtGeom.mjGEOM_CAPSULE, (r,), fromto=(0, 0.004, 0, 0, 0.035, 0),
                mass_from_density=True).density = 1300
    ds = px.add_body(name="th_ds", pos=[0, 0.035, 0])
    _add_joint_and_actuator(spec, ds, "th_ipl", (1, 0, 0), THUMB_RANGES["ipl"], HAND_EFFORT)
    _robot_geom(ds, "th_ds_col", mujoco.mjtGeom.mjGEOM_CAPSULE, (r,), fromto=(0, 0.004, 0, 0, 0.05 - r, 0),
                mass_from_density=True).density = 1300
    _robot_geom(ds, "th_tip_col", mujoco.mjtGeom.mjGEOM_SPHERE, (r * 1.05,), pos=(0, 0.05 - r, 0.002),
                friction=TIP_FRICTION, rgba=(0.95, 0.95, 0.95, 1))
    ds.add_site(name="thumb_tip", pos=[0, 0.05 - r, 0.002], size=[0.004, 0, 0])


def _build_hand(spec: mujoco.MjSpec, flange: mujoco.MjsBody) -> None:
    palm = flange.add_body(name="palm", pos=[0, 0, 0.0])
    # Palm block: 3 cm thick, 13 cm wide, 10 cm long, starting 1.5 cm above the flange (adapter).
    _robot_geom(palm, "palm_col", mujoco.mjtGeom.mjGEOM_BOX, (0.015, 0.068, 0.05), pos=(0, -0.003, 0.065),
                mass_from_density=True).density = 1000
    _robot_geom(palm, "adapter_col", mujoco.mjtGeom.mjGEOM_CYLINDER, (0.035, 0.0075), pos=(0, 0, 0.0075),
                mass_from_density=True).density = 1500
    palm.add_site(name="palm", pos=[-0.015, 0, 0.075], size=[0.006, 0, 0])
    for prefix, site in (("if", "index_tip"), ("mf", "middle_tip"), ("rf", "ring_tip")):
        _finger(spec, palm, prefix, FINGER_Y[prefix], site)
    _thumb(spec, palm)


def build_robot_spec(*, with_base_geom: bool = True) -> mujoco.MjSpec:
    """Build the 22-joint arm + hand as a new ``MjSpec`` (robot base at the world origin).

    Physics options (timestep, integrator, cone) are set by :mod:`adadex.sim.scene`; the spec
    returned here carries MuJoCo's defaults apart from the robot itself.
    """
    spec = mujoco.MjSpec()
    spec.modelname = "adadex_xarm6_leap"
    spec.compiler.degree = False
    # The URDF inertia tensors of link2 violate the triangle inequality by a hair after rounding.
    spec.compiler.balanceinertia = True
    base = spec.worldbody.add_body(name="link_base", pos=[0, 0, 0])
    base.explicitinertial = True
    base.mass = ARM_BASE_MASS
    base.ipos = [0, 0, 0.09103]
    base.fullinertia = [0.00494875, 0.00494174, 0.002219, -3.5e-06, 1.25e-05, 1.67e-06]
    flange = _build_arm(spec, base)
    _build_hand(spec, flange)
    for s in TRACKED_SITES:
        spec.add_sensor(name=f"{s}_pos", type=mujoco.mjtSensor.mjSENS_FRAMEPOS,
                        objtype=mujoco.mjtObj.mjOBJ_SITE, objname=s)
        spec.add_sensor(name=f"{s}_quat", type=mujoco.mjtSensor.mjSENS_FRAMEQUAT,
                        objtype=mujoco.mjtObj.mjOBJ_SITE, objname=s)
    return spec


def joint_limits() -> np.ndarray:
    """(22, 2) joint position limits, rad, in :data:`JOINT_NAMES` order."""
    lim = {link.joint: link.range for link in ARM_LINKS}
    for p in ("if", "mf", "rf"):
        for k, r in FINGER_RANGES.items():
            lim[f"{p}_{k}"] = r
    for k, r in THUMB_RANGES.items():
        lim[f"th_{k}"] = r
    return np.array([lim[n] for n in JOINT_NAMES], dtype=np.float64)


def effort_limits() -> np.ndarray:
    """(22,) actuator effort limits, N·m, in :data:`JOINT_NAMES` order."""
    return np.array([link.effort for link in ARM_LINKS] + [HAND_EFFORT] * 16, dtype=np.float64)


#: A neutral configuration: arm reaching forward above the table, palm down, hand open.
HOME_QPOS = np.array(
    [0.0, -0.35, -0.9, 0.0, 1.25, 0.0]
    + [0.2, 0.0, 0.2, 0.2] * 3
    + [0.6, 0.3, 0.2, 0.2],
    dtype=np.float64,
)

ROBOT_MJCF = asset("robot", "robot.xml")


def robot_mjcf_path() -> Path:
    """Path of the exported MJCF. Generated on first use if the package was installed without it."""
    if not ROBOT_MJCF.exists():
        export_mjcf(ROBOT_MJCF)
    return ROBOT_MJCF


def export_mjcf(path: str | os.PathLike = ROBOT_MJCF) -> Path:
    """Write the builder's robot to ``path`` as MJCF, atomically (temp file + rename).

    Args:
        path: the file to write (default :data:`ROBOT_MJCF`, the packaged ``robot/robot.xml`` asset).

    Returns:
        the path written.
    """
    from adadex.io import atomic_write_text

    spec = build_robot_spec()
    spec.compile()
    return atomic_write_text(path, spec.to_xml())
