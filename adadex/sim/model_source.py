"""Which model the sysid workbench simulates: the built-in scene or any MJCF the user names.

A :class:`ModelSource` is either the built-in scene (the arm + hand on its table, with adadex's
physics options) or a user's MJCF file, used as it is — its own options, contacts and keyframes.
The *robot* of a model is the table of its joints driven by position actuators (joint
transmission, fixed gain, affine bias with ``biasprm[1] = −kp``), in actuator order
(:class:`RobotTable`). Recordings name joints of that table, commands go to their actuators, and
effects act on them by name. On the built-in scene the table is :data:`~adadex.sim.robot.JOINT_NAMES`
with joint id = dof id = actuator id = position in the table.

The table also carries each joint's own sizes — servo gains ``kp`` (N·m/rad) and ``kv``
(N·m·s/rad), ``armature`` (kg·m²), ``effort`` (N·m, the force limit, else ``kp``·1 rad), the mass
the joint carries (kg, its subtree) and its gravity torque at the home pose (N·m) — from which
:mod:`adadex.sim.effects` sizes effect bounds, so one diagnosis fits a 3 N·m/rad finger servo and
a 1500 N·m/rad shoulder alike.

A model is identified by :attr:`ModelSource.model_id`: ``"builtin"``, or the file name with the
SHA-256 of its bytes; model patches record it and refuse another model.

Example
-------
>>> from adadex.sim.model_source import ModelSource
>>> src = ModelSource()
>>> table = src.robot()
>>> src.model_id, table.names[:2], float(table.kp[0])
('builtin', ('arm_j1', 'arm_j2'), 1500.0)
"""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from adadex.errors import AdadexError

BUILTIN_ID = "builtin"


class ModelSourceError(AdadexError, ValueError):
    """A model file that cannot be used: missing, not MJCF, or without position-servoed joints."""


def position_actuated_joints(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(actuator ids, joint ids) of the position servos on hinge or slide joints, in actuator order
    (the first servo of a joint wins)."""
    pos = ((m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT))
           & (m.actuator_gaintype == int(mujoco.mjtGain.mjGAIN_FIXED))
           & (m.actuator_biastype == int(mujoco.mjtBias.mjBIAS_AFFINE))
           & (m.actuator_biasprm[:, 1] < 0))
    acts, jnts, seen = [], [], set()
    for a in np.flatnonzero(pos):
        j = int(m.actuator_trnid[a, 0])
        if j in seen or m.jnt_type[j] not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            continue
        seen.add(j)
        acts.append(int(a))
        jnts.append(j)
    return np.asarray(acts, dtype=np.int64), np.asarray(jnts, dtype=np.int64)


def robot_ids(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joint ids, dof ids, actuator ids) of the robot's table positions in compiled model ``m``.

    Structural effects (history buffers, activations) do not change which joints are servoed or
    their order, so the table positions of a patched model are those of its nominal model.
    """
    acts, jnts = position_actuated_joints(m)
    return jnts, m.jnt_dofadr[jnts].astype(np.int64), acts


@dataclass(frozen=True, eq=False)
class RobotTable:
    """The servoed joints of a model, by name, with the sizes effects are scaled by (see the module
    docstring). Arrays are (J,) in table order."""

    model_id: str
    names: tuple[str, ...]
    limits: np.ndarray          # (J, 2) rad (or m)
    home: np.ndarray            # (J,) the home keyframe's (else qpos0's) positions, inside the limits
    kp: np.ndarray
    kv: np.ndarray
    armature: np.ndarray
    effort: np.ndarray
    carried_mass: np.ndarray
    gravity_torque: np.ndarray
    path: Path | None = None    # the model file (None: the built-in scene)

    @property
    def source(self) -> "ModelSource":
        return ModelSource(self.path)

    @property
    def builtin(self) -> bool:
        return self.model_id == BUILTIN_ID

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, names) -> np.ndarray:
        """Table positions of ``names``; an :class:`~adadex.sim.robot.UnknownJointError` names the model."""
        from adadex.sim.robot import UnknownJointError

        pos = {n: i for i, n in enumerate(self.names)}
        out = []
        for n in names:
            if n not in pos:
                if self.builtin:
                    raise UnknownJointError(n)
                raise UnknownJointError.for_model(n, self.names, self.model_id)
            out.append(pos[n])
        return np.asarray(out, dtype=np.int64)

    @classmethod
    def of(cls, m: mujoco.MjModel, model_id: str, path: Path | None = None) -> "RobotTable":
        jnts, dofs, acts = robot_ids(m)
        if jnts.size == 0:
            raise ModelSourceError(f"{model_id}: no joint is driven by a position actuator (a <position> "
                                   "actuator on a hinge or slide joint); the workbench replays position targets")
        names = tuple(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, int(j)) or f"joint{j}" for j in jnts)
        lim = np.where(m.jnt_limited[jnts, None].astype(bool), m.jnt_range[jnts],
                       np.where(m.actuator_ctrllimited[acts, None].astype(bool), m.actuator_ctrlrange[acts],
                                [[-np.pi, np.pi]]))
        d = mujoco.MjData(m)
        if m.nkey:
            mujoco.mj_resetDataKeyframe(m, d, 0)
        home = np.clip(d.qpos[m.jnt_qposadr[jnts]], lim[:, 0], lim[:, 1])
        d.qpos[m.jnt_qposadr[jnts]] = home
        d.qvel[:] = 0
        mujoco.mj_forward(m, d)
        kp = m.actuator_gainprm[acts, 0].copy()
        limited = m.actuator_forcelimited[acts].astype(bool)
        effort = np.where(limited, np.abs(m.actuator_forcerange[acts]).max(axis=1), kp * 1.0)
        gravity = np.abs(d.qfrc_bias[dofs])
        return cls(model_id, names, lim.astype(float), home.astype(float), kp, -m.actuator_biasprm[acts, 2].copy(),
                   m.dof_armature[dofs].copy(), effort.astype(float), m.body_subtreemass[m.jnt_bodyid[jnts]].copy(),
                   gravity, path)


@dataclass(frozen=True)
class ModelSource:
    """The built-in scene (``path=None``) or a user's MJCF file; see the module docstring.

    Attributes:
        path: the MJCF file (stored resolved; :class:`ModelSourceError` if it is not a file), or
            None (default): the built-in robot and table.
    """

    path: Path | None = None

    def __post_init__(self):
        if self.path is not None:
            p = Path(self.path)
            if not p.is_file():
                raise ModelSourceError(f"{p}: no such model file")
            object.__setattr__(self, "path", p.resolve())

    @property
    def builtin(self) -> bool:
        return self.path is None

    @property
    def model_id(self) -> str:
        if self.path is None:
            return BUILTIN_ID
        return _file_id(str(self.path), os.stat(self.path).st_mtime_ns)

    @property
    def timestep(self) -> float:
        """The model's own physics step, s: the largest step a replay may take."""
        from adadex.sim.scene import PHYSICS_TIMESTEP

        return PHYSICS_TIMESTEP if self.path is None else float(_nominal(self)[0].opt.timestep)

    def spec(self, timestep: float | None = None) -> mujoco.MjSpec:
        """A fresh ``MjSpec`` of the model (built-in: robot + table, no object), with ``timestep``
        if given (the built-in scene also sets its contacts' time constant from it)."""
        if self.path is None:
            from adadex.sim.scene import PhysicsOptions, build_scene_spec

            opts = PhysicsOptions() if timestep is None else PhysicsOptions(timestep=timestep)
            return build_scene_spec(None, options=opts)
        try:
            spec = mujoco.MjSpec.from_file(str(self.path))
        except Exception as e:  # mujoco raises ValueError for parse and compile errors alike
            raise ModelSourceError(f"{self.path}: not a loadable MJCF model ({e})") from None
        if timestep is not None:
            spec.option.timestep = timestep
        return spec

    def compile(self, timestep: float | None = None) -> mujoco.MjModel:
        try:
            return self.spec(timestep).compile()
        except ModelSourceError:
            raise
        except Exception as e:
            raise ModelSourceError(f"{self.path}: the model does not compile ({e})") from None

    def robot(self) -> RobotTable:
        """The servoed joints of the model and their sizes (cached per model)."""
        return _nominal(self)[1]


@functools.lru_cache(maxsize=16)
def _file_id(path: str, mtime_ns: int) -> str:
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    return f"{Path(path).name}#sha256:{digest}"


@functools.lru_cache(maxsize=16)
def _nominal_cached(path: str | None, model_id: str) -> tuple[mujoco.MjModel, RobotTable]:
    src = ModelSource(None if path is None else Path(path))
    m = src.compile()
    return m, RobotTable.of(m, model_id, src.path)


def _nominal(src: ModelSource) -> tuple[mujoco.MjModel, RobotTable]:
    return _nominal_cached(None if src.path is None else str(src.path), src.model_id)


def builtin_robot() -> RobotTable:
    """The built-in robot's table (22 joints, :data:`~adadex.sim.robot.JOINT_NAMES` order)."""
    return ModelSource().robot()


def export_world(path: str | os.PathLike) -> Path:
    """Write the built-in nominal world — robot, table and physics options, no object — as MJCF,
    atomically. ``ModelSource(path)`` replays exactly as the built-in scene does (recordings whose
    period is a multiple of the physics step, such as 60 Hz, bit for bit; tested).

    Args:
        path: the MJCF file to write.

    Returns:
        the path written.
    """
    from adadex.io import atomic_write_text

    spec = ModelSource().spec()
    spec.modelname = "adadex_world"
    model = spec.compile()
    return atomic_write_text(path, _full_precision(spec.to_xml(), model))


#: Per MJCF element, attribute → (compiled-model array, id kind): MuJoCo writes 6 significant digits,
#: so these are rewritten from the compiled model at full precision (``repr``). An attribute whose
#: values span several arrays names them in order (a joint's ``damping`` is its linear damping, then
#: its polynomial terms, ``dof_dampingpoly``); a value no array holds is kept as MuJoCo wrote it.
_EXACT = {
    "body": {"pos": ("body_pos", "body"), "quat": ("body_quat", "body")},
    "inertial": {"pos": ("body_ipos", "parent"), "quat": ("body_iquat", "parent"), "mass": ("body_mass", "parent"),
                 "diaginertia": ("body_inertia", "parent")},
    "geom": {"size": ("geom_size", "geom"), "pos": ("geom_pos", "geom"), "quat": ("geom_quat", "geom"),
             "friction": ("geom_friction", "geom"), "solref": ("geom_solref", "geom"),
             "solimp": ("geom_solimp", "geom")},
    "joint": {"range": ("jnt_range", "joint"), "actuatorfrcrange": ("jnt_actfrcrange", "joint"),
              "axis": ("jnt_axis", "joint"), "pos": ("jnt_pos", "joint"), "armature": ("dof_armature", "dof"),
              "damping": (("dof_damping", "dof_dampingpoly"), "dof"), "frictionloss": ("dof_frictionloss", "dof")},
    "site": {"size": ("site_size", "site"), "pos": ("site_pos", "site"), "quat": ("site_quat", "site")},
    "general": {"ctrlrange": ("actuator_ctrlrange", "actuator"), "forcerange": ("actuator_forcerange", "actuator"),
                "gainprm": ("actuator_gainprm", "actuator"), "biasprm": ("actuator_biasprm", "actuator")},
    "key": {"qpos": ("key_qpos", "key"), "ctrl": ("key_ctrl", "key")},
}
_OBJ = {"body": mujoco.mjtObj.mjOBJ_BODY, "geom": mujoco.mjtObj.mjOBJ_GEOM, "joint": mujoco.mjtObj.mjOBJ_JOINT,
        "site": mujoco.mjtObj.mjOBJ_SITE, "actuator": mujoco.mjtObj.mjOBJ_ACTUATOR, "key": mujoco.mjtObj.mjOBJ_KEY}


def _full_precision(xml: str, m: mujoco.MjModel) -> str:
    """``xml`` with its numbers rewritten from the compiled model ``m`` at full precision."""
    import xml.etree.ElementTree as ET

    root = ET.fromstring(xml)
    for name in ("timestep", "impratio"):
        opt = root.find("option")
        if opt is not None and name in opt.attrib:
            opt.set(name, repr(float(getattr(m.opt, name))))
    parents = {c: p for p in root.iter() for c in p}
    for el in root.iter():
        table = _EXACT.get("general" if el.tag == "general" else el.tag)
        if not table:
            continue
        named = parents[el] if el.tag == "inertial" else el
        tag = "actuator" if el.tag == "general" else named.tag
        if "name" not in named.attrib or tag not in _OBJ:
            continue
        i = mujoco.mj_name2id(m, _OBJ[tag], named.get("name"))
        for attr, (field, kind) in table.items():
            if attr not in el.attrib or i < 0:
                continue
            row = i if kind != "dof" else int(m.jnt_dofadr[i])
            written = el.get(attr).split()
            fields = (field,) if isinstance(field, str) else field
            exact = np.concatenate([np.ravel(getattr(m, f)[row]) for f in fields if hasattr(m, f)])
            el.set(attr, " ".join([repr(float(v)) for v in exact[:len(written)]] + written[len(exact):]))
    ET.indent(root, space="  ")
    return ET.tostring(root, encoding="unicode") + "\n"


def same_model(a: str | None, b: str | None) -> bool:
    """Whether two model ids name the same model (the file name may differ, the content may not)."""
    a, b = a or BUILTIN_ID, b or BUILTIN_ID
    return a.rpartition("#")[2] == b.rpartition("#")[2]
