"""Physical effects: named, parameterized phenomena a simulator may be missing.

One abstraction shared by the tracking envs (``effects=[...]``, domain randomization over effect
parameters), the generation of "measured" data with hidden effects, and the sysid workbench that
fits and ranks them. An effect acts on one or more joints and has parameters, each with bounds, a
nominal value (a typical size when present) and an *absent* value that means "not there": at the
absent value the simulation is bit-identical to the nominal model (tested).

Where an effect acts:

* ``model`` — parameters of the compiled ``MjModel`` (damping, friction loss, armature, servo
  gains, force limits, spring stiffness, body mass). They are set as *absolute* values computed
  from a snapshot of the unmodified model (:class:`ModelBase`), never by incrementing the current
  value, so applying a patch twice, or re-applying with new values during a fit, is safe.
  *Scale* effects (``mass_scale``, ``friction_scale``, ``damping_scale``) re-size the model's own
  values — the nominal numbers were off — so a patch applies them to the snapshot first
  (:meth:`Effect.rescale`) and every other effect acts on top: ``damping`` adds to the scaled
  joint damping, ``payload_mass`` to the scaled link mass (at the scaled link's centre of mass),
  whatever the order in the patch.
* ``structure`` — needs a change to the model's structure before compiling (an actuator history
  buffer for a transport delay, an activation state for a first-order lag); made only when the
  value differs from absent, then the value itself is again a model parameter.
* ``command`` — transforms the commanded joint targets before they reach the servos (backlash).
* ``sensor`` — transforms the measured joint positions (encoder offset).

Per-joint values: ``values`` arrays are ``(len(joints), n_params)``.

:data:`EFFECT_NAMES` are the effects the sysid workbench screens by default: those a joint
trajectory can reveal. The scale effects (:data:`SCALE_EFFECT_NAMES`) are effects like the others
(patches, ``effects=[...]``, fitting with ``adadex sysid fit --add``); they exist for domain
randomization (paper Table 3 scales masses, friction, stiffness and damping) and are not screened:
``friction_scale`` is invisible without contact, and ``mass_scale`` and ``damping_scale`` are
look-alikes of screened effects (``payload_mass``, ``kd_scale``).

Sized to the model: every parameter with a physical unit declares the joint quantity it scales
with (``scales_with``: the servo's ``kp`` or ``kv``, the joint's ``armature``, or for a length the
``reach`` of the link the joint moves, :func:`link_reach`). On the built-in
robot the bounds and nominal sizes are the tuned per-group tables below; on any other model
(:class:`~adadex.sim.model_source.RobotTable`) each joint takes the built-in group nearest in
``kp`` (log scale) and that group's sizes times the ratio of its own quantity to the group's, so a
3 N·m/rad finger servo gets bounds half the built-in finger's and a 300 N·m/rad arm servo three
quarters of the built-in wrist's; a length is sized by the link's reach against the group's
:data:`REACH` (a payload's offset on a forearm reaching 27.5 cm may reach ±27.5 cm, on a 6.8 cm finger ±6.8 cm).
Hooks receive ``jid`` as positions in the robot's table; model hooks map them to the compiled model's
joint, dof and actuator ids (:func:`robot_ids`).

Example
-------
>>> from adadex.sim.effects import get_effect
>>> eff = get_effect("coulomb_friction")
>>> eff.param_names, eff.absent_values().tolist()
(('friction',), [0.0])
"""

from __future__ import annotations

import copy
import difflib
import functools
from collections import OrderedDict
from dataclasses import dataclass
from typing import ClassVar

import mujoco
import numpy as np

from adadex.errors import AdadexError
from adadex.sim.model_source import robot_ids as _robot_ids
from adadex.sim.robot import GAINS, joint_group, joint_index

GROUPS = ("arm_shoulder", "arm_wrist", "finger", "thumb")


@dataclass(frozen=True)
class Param:
    """One effect parameter. ``upper`` is per joint group (arm joints are far stronger than fingers)."""

    name: str
    unit: str
    absent: float
    nominal: dict[str, float]
    lower: dict[str, float]
    upper: dict[str, float]
    #: The joint quantity the sizes scale with on a model other than the built-in: "kp", "kv",
    #: "armature", "reach" (a length on the link: :func:`link_reach`), or None (dimensionless, seconds,
    #: radians).
    scales_with: str | None = None

    def bounds(self, joint: str, robot=None) -> tuple[float, float]:
        g, r = sizing(joint, robot, self.scales_with)
        return self.lower[g] * r, self.upper[g] * r

    def nominal_for(self, joint: str, robot=None) -> float:
        g, r = sizing(joint, robot, self.scales_with)
        return self.nominal[g] * r

    @property
    def composition(self) -> str:
        """How two values of this parameter compose (a draw of domain randomization on top of a
        patch, :meth:`adadex.sim.patch.ModelPatch.composed`), read off the absent value: absent 1
        is a *scale* (``"scale"``: the values multiply — kp 0.3 × a draw of 1.05 is 0.315), absent 0
        an *offset* (``"offset"``: they add — damping, armature, payload, delays, encoder offsets)."""
        if self.absent == 1.0:
            return "scale"
        if self.absent == 0.0:
            return "offset"
        raise EffectError(f"parameter {self.name}: absent value {self.absent:g} is neither 1 (a scale) nor 0 "
                          f"(an offset); say how its values compose")


def sizing(joint: str, robot, scales_with: str | None) -> tuple[str, float]:
    """(built-in group, size ratio) of ``joint`` on ``robot`` (None or the built-in: its own group, 1)."""
    if robot is None or robot.builtin:
        return joint_group(joint), 1.0
    i = int(robot.index([joint])[0])
    kp = max(float(robot.kp[i]), 1e-9)
    group = min(GAINS, key=lambda g: abs(np.log(kp / GAINS[g].kp)))
    if scales_with is None:
        return group, 1.0
    if scales_with == "reach":     # a length: the link's own against the one the group's sizes are made for
        own = float(_reaches(robot.model_id, robot.path)[i]) if robot.path is not None else 0.0
        return group, (own / REACH[group] if own > 0 else 1.0)
    ref = getattr(GAINS[group], scales_with)
    own = float(getattr(robot, scales_with)[i])
    if own <= 0:  # a servo without damping or a joint without armature: size as the stiffness says
        own, ref = kp, GAINS[group].kp
    return group, own / ref


def robot_ids(m: mujoco.MjModel, jid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joint ids, dof ids, actuator ids) in compiled model ``m`` of robot-table positions ``jid``."""
    key = (m.nu, m.njnt, m.actuator_trnid.tobytes())
    ids = _IDS.get(key)
    if ids is None:
        ids = _IDS[key] = _robot_ids(m)
    jid = np.asarray(jid, dtype=np.int64)
    return ids[0][jid], ids[1][jid], ids[2][jid]


_IDS: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _per_group(arm_shoulder: float, arm_wrist: float, hand: float) -> dict[str, float]:
    return {"arm_shoulder": arm_shoulder, "arm_wrist": arm_wrist, "finger": hand, "thumb": hand}


#: The link reach (m) each built-in group's lengths are made for: a payload's offset is bounded by ± this
#: (on the built-in arm's long shoulder links, its wrist links, the finger links). On another model a
#: length scales with the link's own reach (:func:`link_reach`) against its group's.
REACH = _per_group(0.2, 0.1, 0.02)


def link_reach(m: mujoco.MjModel, jnt: int) -> float:
    """The reach (m) of the link joint ``jnt`` (model joint id) moves (:func:`link_bodies`): the largest
    distance from the joint's axis point to the link — the far side of its geoms' bounding spheres, the
    origins and joint anchors of the links it carries, its bodies' centres of mass. Why: where on a link a
    load can hang is a matter of the link's size, not of its servo's group (a user robot's links have
    lengths of their own). The link is rigid, so the model's reference pose gives it; 0 for a link with
    nothing beyond its axis point."""
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    bodies = link_bodies(m, [jnt])[0]
    inside = np.isin(np.arange(m.nbody), bodies)
    carried = np.flatnonzero(inside[m.body_parentid] & ~inside)
    carried = carried[carried != 0]
    geoms = np.flatnonzero(inside[m.geom_bodyid])
    origin = d.xanchor[jnt]
    far = [np.linalg.norm(d.geom_xpos[geoms] - origin, axis=1) + m.geom_rbound[geoms],
           np.linalg.norm(d.xpos[carried] - origin, axis=1),
           np.linalg.norm(d.xanchor[np.isin(m.jnt_bodyid, carried)] - origin, axis=1),
           np.linalg.norm(d.xipos[bodies] - origin, axis=1)]
    return float(max((float(f.max()) for f in far if f.size), default=0.0))


@functools.lru_cache(maxsize=16)
def _reaches(model_id: str, path) -> np.ndarray:
    """:func:`link_reach` of every joint of a model's robot table, in table order (cached per model)."""
    from adadex.sim.model_source import ModelSource

    m = ModelSource(path).compile()
    return np.array([link_reach(m, int(j)) for j in _robot_ids(m)[0]])


def _same(v: float) -> dict[str, float]:
    return _per_group(v, v, v)


class EffectError(AdadexError, ValueError):
    """A bad effect name, joint list or parameter value."""


@dataclass
class ModelBase:
    """Snapshot of the fields effects edit, taken from an unmodified compiled model."""

    dof_damping: np.ndarray
    dof_frictionloss: np.ndarray
    dof_armature: np.ndarray
    jnt_stiffness: np.ndarray
    gainprm: np.ndarray
    biasprm: np.ndarray
    forcerange: np.ndarray
    actfrcrange: np.ndarray
    body_mass: np.ndarray
    actuator_delay: np.ndarray
    dynprm: np.ndarray
    body_inertia: np.ndarray
    geom_friction: np.ndarray
    body_ipos: np.ndarray                    # a payload moves its body's centre of mass …
    body_iquat: np.ndarray                   # … and turns its principal axes
    forcelimited: np.ndarray | None = None   # a torque limit may limit a servo the model leaves unlimited

    def restore(self, m: mujoco.MjModel) -> None:
        """Put every field effects edit back to this snapshot (before applying a new patch)."""
        m.dof_damping[:] = self.dof_damping
        m.dof_frictionloss[:] = self.dof_frictionloss
        m.dof_armature[:] = self.dof_armature
        m.jnt_stiffness[:] = self.jnt_stiffness
        m.actuator_gainprm[:] = self.gainprm
        m.actuator_biasprm[:] = self.biasprm
        m.actuator_forcerange[:] = self.forcerange
        m.jnt_actfrcrange[:] = self.actfrcrange
        mass_changed = not (np.array_equal(m.body_mass, self.body_mass)
                            and np.array_equal(m.body_inertia, self.body_inertia)
                            and np.array_equal(m.body_ipos, self.body_ipos)
                            and np.array_equal(m.body_iquat, self.body_iquat))
        m.body_mass[:] = self.body_mass
        m.body_inertia[:] = self.body_inertia
        m.body_ipos[:] = self.body_ipos
        m.body_iquat[:] = self.body_iquat
        if mass_changed:
            set_const(m)
        m.actuator_delay[:] = self.actuator_delay
        m.actuator_dynprm[:] = self.dynprm
        m.geom_friction[:] = self.geom_friction
        if self.forcelimited is not None:
            m.actuator_forcelimited[:] = self.forcelimited

    @classmethod
    def of(cls, m: mujoco.MjModel) -> "ModelBase":
        return cls(m.dof_damping.copy(), m.dof_frictionloss.copy(), m.dof_armature.copy(),
                   m.jnt_stiffness.copy(), m.actuator_gainprm.copy(), m.actuator_biasprm.copy(),
                   m.actuator_forcerange.copy(), m.jnt_actfrcrange.copy(), m.body_mass.copy(),
                   m.actuator_delay.copy(), m.actuator_dynprm.copy(), m.body_inertia.copy(),
                   m.geom_friction.copy(), m.body_ipos.copy(), m.body_iquat.copy(),
                   forcelimited=m.actuator_forcelimited.copy())

    def copy(self) -> "ModelBase":
        return copy.deepcopy(self)


_SCRATCH: OrderedDict[tuple, mujoco.MjData] = OrderedDict()


def set_const(m: mujoco.MjModel) -> None:
    """``mj_setConst`` after a mass change (derived constants: subtree masses, inverse weights),
    with a scratch ``MjData`` kept per model structure (allocating one costs ~10× the call)."""
    key = (m.signature, m.nC, m.nbvh, m.nbvhdynamic)
    d = _SCRATCH.pop(key, None)
    if d is None:
        d = mujoco.MjData(m)
    _SCRATCH[key] = d
    while len(_SCRATCH) > 8:
        _SCRATCH.popitem(last=False)
    mujoco.mj_setConst(m, d)


_LINKS: OrderedDict[tuple, tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()


def _links(m: mujoco.MjModel, jid):
    """Per joint, the bodies it moves directly; then all those bodies, with the index (into ``jid``)
    of the joint moving each, and the same for their geoms. Kept per model structure and joint list
    (a reset asks once per world)."""
    jid = np.asarray(jid, dtype=np.int64)
    key = (m.signature, jid.tobytes())
    if key not in _LINKS:
        owner = np.arange(m.nbody)
        for b in range(1, m.nbody):          # parents come before children in a compiled model
            if m.body_jntnum[b] == 0:
                owner[b] = owner[m.body_parentid[b]]
        bodies = [np.flatnonzero(owner == m.jnt_bodyid[j]) for j in jid]
        body_of = np.full(m.nbody, -1)
        for k, b in enumerate(bodies):
            body_of[b] = k
        all_bodies = np.flatnonzero(body_of >= 0)
        all_geoms = np.flatnonzero(body_of[m.geom_bodyid] >= 0)
        _LINKS[key] = (bodies, all_bodies, body_of[all_bodies], all_geoms, body_of[m.geom_bodyid[all_geoms]])
        while len(_LINKS) > 64:
            _LINKS.popitem(last=False)
    return _LINKS[key]


def link_bodies(m: mujoco.MjModel, jid) -> list[np.ndarray]:
    """Per joint, the bodies it moves directly: its own body and the bodies welded below it (those
    whose nearest ancestor carrying a joint is the joint's body)."""
    return _links(m, jid)[0]


class Effect:
    """Base class; subclasses set the class attributes and override the hooks of their stage."""

    name: ClassVar[str]
    stage: ClassVar[str]                       # "model" | "structure" | "command" | "sensor"
    params: ClassVar[tuple[Param, ...]]
    #: Alternatives the data of a position servo cannot tell apart from this effect.
    lookalikes: ClassVar[tuple[str, ...]] = ()

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def absent_values(self) -> np.ndarray:
        return np.array([p.absent for p in self.params])

    @property
    def compositions(self) -> tuple[str, ...]:
        """Per parameter, ``"scale"`` or ``"offset"`` (:attr:`Param.composition`)."""
        return tuple(p.composition for p in self.params)

    def nominal_values(self, joints, robot=None) -> np.ndarray:
        return np.array([[p.nominal_for(j, robot) for p in self.params] for j in joints])

    def bounds(self, joints, robot=None) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper), each (len(joints), n_params), sized to ``robot`` (default: the built-in);
        cached per joint list and model (a reset validates one patch per world)."""
        key = (tuple(joints), None if robot is None else robot.model_id)
        cache = self.__dict__.setdefault("_bounds", {})
        if key not in cache:
            lo = np.array([[p.bounds(j, robot)[0] for p in self.params] for j in key[0]])
            hi = np.array([[p.bounds(j, robot)[1] for p in self.params] for j in key[0]])
            lo.flags.writeable = hi.flags.writeable = False
            if len(cache) > 256:
                cache.clear()
            cache[key] = (lo, hi)
        return cache[key]

    def is_absent(self, values: np.ndarray) -> bool:
        return bool(np.all(np.asarray(values) == self.absent_values()))

    def validate(self, joints, values, robot=None) -> np.ndarray:
        """Check joint names and values (shape, finite, in bounds on ``robot``); return values as (J, P).

        Values may give the leading parameters only, the others are then at their absent values: a
        scalar, or one value per joint, is the first parameter (``payload_mass`` 0.6 is 0.6 kg at offset 0),
        a (J, k) array the first k."""
        joints = list(joints)
        if not joints:
            raise EffectError(f"{self.name}: no joints given")
        joint_index(joints) if robot is None else robot.index(joints)
        if len(set(joints)) != len(joints):
            raise EffectError(f"{self.name}: duplicate joints in {joints}")
        v = np.asarray(values, dtype=float)
        J, P = len(joints), len(self.params)
        if v.ndim == 0:
            v = np.broadcast_to(v, (J, 1))
        elif v.ndim == 1 and v.shape[0] == P:
            v = np.broadcast_to(v, (J, P))
        elif v.ndim == 1 and v.shape[0] == J:
            v = v.reshape(-1, 1)
        if v.ndim == 2 and v.shape[0] == J and 1 <= v.shape[1] < P:
            v = np.concatenate([v, np.broadcast_to(self.absent_values()[v.shape[1]:], (J, P - v.shape[1]))], axis=1)
        if v.shape != (len(joints), len(self.params)):
            raise EffectError(f"{self.name}: values must have shape ({len(joints)}, {len(self.params)}) "
                              f"for joints {joints} and params {self.param_names}, got {np.shape(values)}")
        bad = np.argwhere(~np.isfinite(v))
        if bad.size:
            j, p = bad[0]
            raise EffectError(f"{self.name}: non-finite {self.params[p].name}={v[j, p]:g} {self.params[p].unit} "
                              f"on {joints[j]}")
        lo, hi = self.bounds(joints, robot)
        bad = np.argwhere((v < lo - 1e-12) | (v > hi + 1e-12))
        if bad.size:
            j, p = bad[0]
            raise EffectError(f"{self.name}: {self.params[p].name}={v[j, p]:g} {self.params[p].unit} on "
                              f"{joints[j]} is outside [{lo[j, p]:g}, {hi[j, p]:g}]")
        return np.array(v)

    # Hooks. ``jid`` are positions in the robot's table (built-in: indices into JOINT_NAMES = joint ids
    # = dof ids = actuator ids); model hooks map them with :func:`robot_ids`.
    def edit_spec(self, spec: mujoco.MjSpec, joints: list[str], values: np.ndarray, timestep: float) -> None:
        """Structural change before compiling (only ``structure`` effects)."""

    def apply_model(self, m: mujoco.MjModel, base: ModelBase, jid: np.ndarray, values: np.ndarray) -> None:
        """Set absolute parameter values on a compiled model (``model`` and ``structure`` effects)."""

    #: Scale effects re-size the snapshot's own values (:meth:`rescale`) before any effect applies.
    rescales: ClassVar[bool] = False

    def rescale(self, base: ModelBase, m: mujoco.MjModel, jid: np.ndarray, values: np.ndarray) -> None:
        """Scale the nominal values in ``base`` (a copy) in place (scale effects only)."""

    def transform_command(self, command: np.ndarray, jid: np.ndarray, values: np.ndarray, dt: float) -> np.ndarray:
        """(S, T, J_robot) commanded targets → what the servos receive (``command`` effects)."""
        return command

    def transform_measurement(self, qpos: np.ndarray, jid: np.ndarray, values: np.ndarray) -> np.ndarray:
        """(S, T, J_robot) true joint positions → what the encoders report (``sensor`` effects)."""
        return qpos


class Damping(Effect):
    """Extra viscous joint damping, τ = −b·q̇ (parameter b, N·m·s/rad, added to the model's).

    Residual signature: the measured joint lags and is attenuated more than the model, increasingly
    with frequency and velocity; error ∝ velocity, no dead zone, symmetric in direction.
    On a position servo it is indistinguishable from a larger derivative gain (``kd_scale``).
    """

    name, stage = "damping", "model"
    params = (Param("damping", "N·m·s/rad", 0.0, _per_group(5.0, 1.0, 0.05),
                    _same(0.0), _per_group(60.0, 15.0, 0.6), "kv"),)
    lookalikes = ("kd_scale",)

    def apply_model(self, m, base, jid, values):
        dof = robot_ids(m, jid)[1]
        m.dof_damping[dof] = base.dof_damping[dof] + values[:, 0]


class CoulombFriction(Effect):
    """Coulomb (dry) joint friction of magnitude f (N·m), MuJoCo ``frictionloss``, added to the model's.

    Residual signature: error concentrated at velocity reversals (stick, then a jump), a dead zone
    around small commanded motions; relatively larger at small amplitude, nearly independent of
    frequency.
    """

    name, stage = "coulomb_friction", "model"
    params = (Param("friction", "N·m", 0.0, _per_group(3.0, 1.0, 0.05),
                    _same(0.0), _per_group(25.0, 10.0, 0.4), "kp"),)

    def apply_model(self, m, base, jid, values):
        dof = robot_ids(m, jid)[1]
        m.dof_frictionloss[dof] = base.dof_frictionloss[dof] + values[:, 0]


class Armature(Effect):
    """Extra reflected rotor inertia at the joint (kg·m²), added to the model's armature.

    Residual signature: error grows with acceleration (with frequency² at fixed amplitude); the
    servo resonance moves lower, overshoot on fast reversals; nothing at constant velocity.
    """

    name, stage = "armature", "model"
    params = (Param("armature", "kg·m²", 0.0, _per_group(0.2, 0.05, 0.003),
                    _same(0.0), _per_group(2.0, 0.5, 0.03), "armature"),)
    lookalikes = ("payload_mass",)

    def apply_model(self, m, base, jid, values):
        dof = robot_ids(m, jid)[1]
        m.dof_armature[dof] = base.dof_armature[dof] + values[:, 0]


class ActuatorDelay(Effect):
    """Pure transport delay τ (s) between command and servo: the servo tracks the command of t − τ.

    Implemented with MuJoCo 4 actuator history (``delay``/``nsample``), read with linear
    interpolation so the delay is continuous rather than quantized to the physics step.
    Residual signature: phase lag growing linearly with frequency (φ = 2πfτ), gain unchanged; the
    error looks like the command's derivative times τ.
    """

    name, stage = "actuator_delay", "structure"
    params = (Param("delay", "s", 0.0, _same(0.03), _same(0.0), _same(0.1)),)
    MAX_DELAY = 0.1

    def edit_spec(self, spec, joints, values, timestep):
        nsample = int(np.ceil(self.MAX_DELAY / timestep)) + 2
        for j, v in zip(joints, values[:, 0]):
            if v != self.absent_values()[0]:
                act = servo_of(spec, j)
                act.nsample = nsample
                act.interp = 1

    def apply_model(self, m, base, jid, values):
        m.actuator_delay[robot_ids(m, jid)[2]] = values[:, 0]


class ActuatorLag(Effect):
    """First-order lag τ (s) on the servo target: the target follows the command as ẋ = (u − x)/τ.

    Implemented as a MuJoCo ``filterexact`` actuator activation. Residual signature: low-pass —
    amplitude ratio 1/√(1 + (2πfτ)²) and phase lag atan(2πfτ), saturating at 90°, unlike a delay.
    """

    name, stage = "actuator_lag", "structure"
    params = (Param("tau", "s", 0.0, _same(0.04), _same(0.0), _same(0.3)),)

    def edit_spec(self, spec, joints, values, timestep):
        for j, v in zip(joints, values[:, 0]):
            if v != 0.0:
                act = servo_of(spec, j)
                act.dyntype = mujoco.mjtDyn.mjDYN_FILTEREXACT
                act.dynprm = [float(v)] + [0.0] * 9
                act.actlimited = mujoco.mjtLimited.mjLIMITED_FALSE

    def apply_model(self, m, base, jid, values):
        act = robot_ids(m, jid)[2]
        lagged = m.actuator_dyntype[act] == int(mujoco.mjtDyn.mjDYN_FILTEREXACT)
        m.actuator_dynprm[act[lagged], 0] = np.maximum(values[lagged, 0], 1e-6)


class TorqueLimit(Effect):
    """Servo torque saturation at a fraction of the nominal effort limit (absent = 1, no change).

    The effort is the servo's force limit in the model (a servo without one: ``kp`` · 1 rad).

    Residual signature: error only above an amplitude/frequency where the demanded torque exceeds
    the limit; clipped, triangular-looking motion; none at small amplitude.
    """

    name, stage = "torque_limit", "model"
    params = (Param("fraction", "× effort", 1.0, _per_group(0.7, 0.6, 0.5), _same(0.05), _same(1.0)),)

    def apply_model(self, m, base, jid, values):
        jnt, _, act = robot_ids(m, jid)
        limited = m.actuator_forcelimited[act].astype(bool)
        effort = np.where(limited, np.abs(base.forcerange[act]).max(axis=1), base.gainprm[act, 0])
        lim = effort * values[:, 0]
        m.actuator_forcelimited[act] = 1
        m.actuator_forcerange[act, 0] = -lim
        m.actuator_forcerange[act, 1] = lim
        m.jnt_actfrcrange[jnt, 0] = -lim
        m.jnt_actfrcrange[jnt, 1] = lim


class KpScale(Effect):
    """Proportional gain of the position servo scaled by s (absent = 1).

    Residual signature: a different steady-state sag under load and a different bandwidth:
    amplitude and phase errors that change with frequency; static offset under gravity.
    """

    name, stage = "kp_scale", "model"
    params = (Param("scale", "×", 1.0, _same(0.7), _same(0.2), _same(3.0)),)

    def apply_model(self, m, base, jid, values):
        act = robot_ids(m, jid)[2]
        m.actuator_gainprm[act, 0] = base.gainprm[act, 0] * values[:, 0]
        m.actuator_biasprm[act, 1] = base.biasprm[act, 1] * values[:, 0]


class KdScale(Effect):
    """Derivative gain of the position servo scaled by s (absent = 1).

    Residual signature: like extra viscous damping (``damping``) — they are one hypothesis for a
    position servo; velocity-proportional lag and attenuation.
    """

    name, stage = "kd_scale", "model"
    params = (Param("scale", "×", 1.0, _same(2.0), _same(0.2), _same(8.0)),)
    lookalikes = ("damping",)

    def apply_model(self, m, base, jid, values):
        act = robot_ids(m, jid)[2]
        m.actuator_biasprm[act, 2] = base.biasprm[act, 2] * values[:, 0]


class PayloadMass(Effect):
    """Extra point mass (kg) on the link the joint moves, ``offset`` (m) from the link's combined centre
    of mass along the link's distal axis: one load where it hangs, found in mass and place.

    The link is the joint's body and the bodies welded to it (:func:`link_bodies`; on the built-in
    arm_j6, link6 and the palm); its combined centre of mass c (the snapshot's masses) is the reference
    and the distal axis the unit vector from the joint's axis point (``jnt_pos``) through c
    (:func:`payload_point`). Offset 0 is c (the link's centre of mass does not move); negative is towards
    the joint: on arm_j6 −4.33 cm is the flange, +1.17 cm the palm's own centre of mass, −5.28 cm link6's
    (where payload_mass hung its mass before 2026-11-27). Why a position: a joint feels the load's mass
    times its lever arm to the load in the sag and times its square in the inertia, so one mass at a
    fixed point cannot fit a load a few centimetres from it (a mass at the flange, fitted at c, came out
    as 0.752 kg on arm_j5's link for 0.6 kg). The offset's nominal size is its prior scale in the
    diagnosis (5 cm, 3 cm, 5 mm on shoulder, wrist and hand links; bounds ±20, ±10, ±2 cm). On another
    model both scale with the link's own reach (:func:`link_reach`: the bounds ± the reach, the prior a
    quarter of it, 0.3 on links sized as the built-in wrist's): a prior and bounds sized for the built-in
    wrist held a load 5 cm beyond a 25 cm forearm's centre of mass at +2.5 cm (0.340 kg for 0.3 kg).

    The mass is attached to the joint's own body: its mass grows by m, its centre of mass
    (``body_ipos``) moves to the mass-weighted mean of the old one and the point, and its inertia
    tensor about the new centre of mass gains the parallel-axis terms of both, re-diagonalized into
    ``body_inertia`` and ``body_iquat`` (a proper rotation). Everything is computed from the snapshot
    with numpy and MuJoCo's own quaternion functions (no torch), so a patch applies it once whatever the
    model held; at 0 kg the body is the snapshot's, bit for bit, whatever the offset; offset 0 is the
    mass alone, bit for bit.

    Residual signature: error growing with acceleration on that joint and its parents, and a static sag
    under gravity on the joints that carry it (pose dependent); the joints near the load (the wrist for a
    hand load) tell the offset, the far ones (shoulder, elbow) mostly the mass.
    """

    name, stage = "payload_mass", "model"
    params = (Param("mass", "kg", 0.0, _per_group(0.5, 0.3, 0.02),
                    _same(0.0), _per_group(5.0, 3.0, 0.2), "kp"),
              Param("offset", "m", 0.0, _per_group(0.05, 0.03, 0.005),
                    _per_group(-0.2, -0.1, -0.02), _per_group(0.2, 0.1, 0.02), "reach"))
    lookalikes = ("armature",)

    def apply_model(self, m, base, jid, values):
        jnt = robot_ids(m, jid)[0]
        for bodies, j, mass, offset in zip(_links(m, jnt)[0], jnt, values[:, 0], values[:, 1]):
            body = m.jnt_bodyid[j]
            m.body_mass[body] = base.body_mass[body]
            m.body_ipos[body] = base.body_ipos[body]
            m.body_iquat[body] = base.body_iquat[body]
            m.body_inertia[body] = base.body_inertia[body]
            if mass != 0.0:
                _add_point_mass(m, base, body, float(mass), payload_point(m, base, int(j), bodies, float(offset)))
        set_const(m)


def payload_point(m: mujoco.MjModel, base: ModelBase, jnt: int, bodies: np.ndarray,
                  offset: float = 0.0) -> np.ndarray:
    """A point on the link of joint ``jnt`` (model joint id), in the frame of the joint's body: the combined
    centre of mass c of the link's ``bodies`` (:func:`link_bodies`, ``base``'s masses) moved ``offset``
    metres along the link's distal axis, the unit vector from the joint's axis point (``jnt_pos``) to c
    (the joint's axis when c is on that point): where :class:`PayloadMass` hangs its mass. Offset 0 is c
    itself, exactly. :class:`EffectError` naming the offset if it is not finite."""
    if not np.isfinite(offset):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, jnt)
        raise EffectError(f"payload_mass: offset={offset:g} m on joint {name!r} is not finite")
    c = _link_com(m, base, int(m.jnt_bodyid[jnt]), bodies)
    if offset == 0.0:
        return c
    d = c - m.jnt_pos[jnt]
    n = float(np.linalg.norm(d))
    u = d / n if n > 1e-9 else m.jnt_axis[jnt] / np.linalg.norm(m.jnt_axis[jnt])
    return c + offset * u


def _link_com(m: mujoco.MjModel, base: ModelBase, body: int, bodies: np.ndarray) -> np.ndarray:
    """The combined centre of mass of ``bodies`` (``body`` and bodies welded below it, parents first)
    with ``base``'s masses, in ``body``'s frame; ``body``'s own when the link has no mass."""
    pose = {int(body): (np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))}   # each body's pose in body's frame
    weighted, total = np.zeros(3), 0.0
    for b in bodies:
        b = int(b)
        if b not in pose:
            pos, quat = pose[int(m.body_parentid[b])]
            pose[b] = (pos + _rotate(quat, m.body_pos[b]), _mul_quat(quat, m.body_quat[b]))
        pos, quat = pose[b]
        weighted += base.body_mass[b] * (pos + _rotate(quat, base.body_ipos[b]))
        total += base.body_mass[b]
    return weighted / total if total > 0 else base.body_ipos[body].copy()


def _rotate(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    out = np.empty(3)
    mujoco.mju_rotVecQuat(out, np.asarray(vec, dtype=np.float64), np.asarray(quat, dtype=np.float64))
    return out


def _mul_quat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    mujoco.mju_mulQuat(out, np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    return out


def _add_point_mass(m: mujoco.MjModel, base: ModelBase, body: int, mass: float, point: np.ndarray) -> None:
    """Set ``body`` to ``base``'s body plus a point ``mass`` at ``point`` (body frame): mass, centre of
    mass, and the inertia tensor about the new centre of mass (parallel axis), re-diagonalized."""
    m0, c0 = float(base.body_mass[body]), base.body_ipos[body]
    total = m0 + mass
    if not (np.isfinite(mass) and total > 0):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body)
        raise EffectError(f"payload_mass: mass={mass:g} kg on body {name!r} leaves it a mass of {total:g} kg; "
                          f"a payload must leave a positive, finite mass")
    axes = np.empty(9)
    mujoco.mju_quat2Mat(axes, np.asarray(base.body_iquat[body], dtype=np.float64))
    axes = axes.reshape(3, 3)                                   # principal axes, as columns in the body frame
    com = (m0 * c0 + mass * point) / total

    def shift(r):                                               # inertia of a unit point mass at r about 0
        return np.dot(r, r) * np.eye(3) - np.outer(r, r)

    inertia = (axes * base.body_inertia[body]) @ axes.T + m0 * shift(c0 - com) + mass * shift(point - com)
    moments, vecs = np.linalg.eigh(0.5 * (inertia + inertia.T))
    moments, vecs = moments[::-1], vecs[:, ::-1]                 # largest first, as MuJoCo's compiler
    if np.linalg.det(vecs) < 0:
        vecs = vecs * np.array([1.0, 1.0, -1.0])                 # a proper rotation (det +1)
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(vecs).ravel())
    m.body_mass[body] = total
    m.body_ipos[body] = com
    m.body_iquat[body] = -quat if quat[0] < 0 else quat          # canonical, w >= 0
    m.body_inertia[body] = np.maximum(moments, 0.0)


class JointSpring(Effect):
    """A torsional spring to the joint's zero position, τ = −k·q (N·m/rad).

    Residual signature: a position-dependent static offset (pulled toward 0), larger where q is far
    from 0 and the servo is weak; stiffer, higher-frequency dynamics.
    """

    name, stage = "joint_spring", "model"
    params = (Param("stiffness", "N·m/rad", 0.0, _per_group(8.0, 4.0, 0.3),
                    _same(0.0), _per_group(1000.0, 200.0, 5.0), "kp"),)

    def apply_model(self, m, base, jid, values):
        jnt = robot_ids(m, jid)[0]
        m.jnt_stiffness[jnt] = base.jnt_stiffness[jnt] + values[:, 0]


class EncoderOffset(Effect):
    """A constant bias on the measured joint position (rad): reported = true + offset.

    Residual signature: a constant error, identical at every frequency, amplitude and pose.
    """

    name, stage = "encoder_offset", "sensor"
    params = (Param("offset", "rad", 0.0, _same(0.02), _same(-0.1), _same(0.1)),)

    def transform_measurement(self, qpos, jid, values):
        out = qpos.copy()
        out[..., jid] += values[:, 0]
        return out


class Backlash(Effect):
    """Backlash: a dead band of total width 2b (rad) between command and joint on reversal.

    The servo target follows the command through a play operator: it moves only once the command
    has travelled b past it. Residual signature: after every velocity reversal the joint waits
    while the command travels 2b; error ≈ ±b, sign following the direction of motion; relatively
    large at small amplitude.
    """

    name, stage = "backlash", "command"
    params = (Param("half_width", "rad", 0.0, _same(0.01), _same(0.0), _same(0.05)),)

    def transform_command(self, command, jid, values, dt):
        out = command.copy()
        b = values[:, 0]
        x = command[:, 0, jid].copy()
        for t in range(command.shape[1]):
            x = np.clip(x, command[:, t, jid] - b, command[:, t, jid] + b)
            out[:, t, jid] = x
        return out


class MassScale(Effect):
    """Masses and inertias of the links the joint moves (its body and the bodies welded to it)
    scaled by s (absent = 1); a payload (``payload_mass``) adds to the scaled mass.

    Residual signature: like a payload spread over the link — error growing with acceleration on
    that joint and its parents, a static sag under gravity on the joints that carry it.
    """

    name, stage = "mass_scale", "model"
    params = (Param("scale", "×", 1.0, _same(1.2), _same(0.3), _same(3.0)),)
    lookalikes = ("payload_mass", "armature")
    rescales = True

    def rescale(self, base, m, jid, values):
        _, bodies, joint_of, _, _ = _links(m, robot_ids(m, jid)[0])
        base.body_mass[bodies] *= values[joint_of, 0]
        base.body_inertia[bodies] *= values[joint_of, 0][:, None]

    def apply_model(self, m, base, jid, values):
        bodies = _links(m, robot_ids(m, jid)[0])[1]
        m.body_mass[bodies] = base.body_mass[bodies]
        m.body_inertia[bodies] = base.body_inertia[bodies]
        set_const(m)


class FrictionScale(Effect):
    """Sliding friction coefficient of the geoms of the links the joint moves scaled by s (absent = 1).

    Residual signature: none in free motion — only contacts feel it (a grasp slips or holds
    differently); joint trajectories without contact cannot reveal it.
    """

    name, stage = "friction_scale", "model"
    params = (Param("scale", "×", 1.0, _same(0.8), _same(0.2), _same(3.0)),)
    rescales = True

    def rescale(self, base, m, jid, values):
        _, _, _, geoms, joint_of = _links(m, robot_ids(m, jid)[0])
        base.geom_friction[geoms, 0] *= values[joint_of, 0]

    def apply_model(self, m, base, jid, values):
        geoms = _links(m, robot_ids(m, jid)[0])[3]
        m.geom_friction[geoms, 0] = base.geom_friction[geoms, 0]


class DampingScale(Effect):
    """All viscous damping at the joint — its passive damping and its servo's derivative gain —
    scaled by s (absent = 1); ``damping`` and ``kd_scale`` act on top of the scaled values.

    Residual signature: like extra (s > 1) or missing (s < 1) viscous damping: velocity-proportional
    lag and attenuation, no dead zone.
    """

    name, stage = "damping_scale", "model"
    params = (Param("scale", "×", 1.0, _same(1.5), _same(0.2), _same(8.0)),)
    lookalikes = ("damping", "kd_scale")
    rescales = True

    def rescale(self, base, m, jid, values):
        _, dof, act = robot_ids(m, jid)
        base.dof_damping[dof] *= values[:, 0]
        base.biasprm[act, 2] *= values[:, 0]

    def apply_model(self, m, base, jid, values):
        _, dof, act = robot_ids(m, jid)
        m.dof_damping[dof] = base.dof_damping[dof]
        m.actuator_biasprm[act, 2] = base.biasprm[act, 2]


def servo_of(spec: mujoco.MjSpec, joint: str):
    """The position actuator of ``joint`` in ``spec`` (the built-in names it ``<joint>_pos``)."""
    act = spec.actuator(f"{joint}_pos")
    if act is not None and act.target == joint:
        return act
    for act in spec.actuators:
        if act.target == joint and act.trntype == mujoco.mjtTrn.mjTRN_JOINT and act.biasprm[1] < 0:
            return act
    raise EffectError(f"no position actuator drives joint {joint!r}")


EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Damping(), CoulombFriction(), Armature(), ActuatorDelay(), ActuatorLag(), TorqueLimit(),
    KpScale(), KdScale(), PayloadMass(), JointSpring(), EncoderOffset(), Backlash(),
    MassScale(), FrictionScale(), DampingScale(),
)}
#: Scale effects: for domain randomization and patches, not screened by the workbench by default.
SCALE_EFFECT_NAMES: tuple[str, ...] = ("mass_scale", "friction_scale", "damping_scale")
#: The effects the sysid workbench screens by default (see the module docstring).
EFFECT_NAMES: tuple[str, ...] = tuple(n for n in EFFECTS if n not in SCALE_EFFECT_NAMES)


def get_effect(name: str) -> Effect:
    """The effect called ``name``; :class:`EffectError` with suggestions otherwise.

    Args:
        name: an effect's name (a key of :data:`EFFECTS`, e.g. ``"kp_scale"``).

    Returns:
        the :class:`Effect`.

    Raises:
        EffectError: no effect has that name (the message suggests close names).

    Examples:
        >>> get_effect("kp_scale").name
        'kp_scale'
    """
    try:
        return EFFECTS[name]
    except KeyError:
        close = difflib.get_close_matches(str(name), tuple(EFFECTS), n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise EffectError(f"unknown effect {name!r}: known effects are {', '.join(EFFECTS)}{hint}") from None

