"""Kinematic replay of references in MuJoCo, and the feasibility filter (paper: single hand, no
hand–arm collision, reachable at every frame).

:class:`KinematicReplay` plays a reference's joint positions in the scene — robot joints set
directly, the object placed at its reference pose, no dynamics — and reads back the tracked-link
poses and the contacts. The simulation itself never lets the hand touch the arm (robot geoms do
not collide with each other, for speed), so the replay model switches hand–arm and robot–table
contacts on and object contacts off: fingertips sinking into the object are part of the
references' intended noise, not a reason to reject them.

:func:`check` returns ``None`` for a feasible reference or a :class:`Rejection` naming the reason
and the first offending frame.

Example
-------
>>> import numpy as np
>>> from adadex.data.reference import Reference
>>> from adadex.sim.robot import HOME_QPOS
>>> ref = Reference.from_joint_positions(np.tile(HOME_QPOS, (310, 1)), np.tile([0.45, 0, 0.026, 1, 0, 0, 0], (310, 1)),
...                                      object_name="cube_050", instruction="wait", group_id=0)
>>> check(ref) is None
True
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import mujoco
import numpy as np

from adadex.data.reference import Reference, WindowTooShortError
from adadex.sim.robot import NUM_JOINTS, TRACKED_SITES
from adadex.sim.scene import OBJECT_BODY, OBJECT_QPOS, build_scene_model, descends

_ARM, _HAND, _WORLD = 4, 8, 16


@dataclass(frozen=True)
class FeasibilityConfig:
    """Thresholds of :func:`check` (m)."""

    max_palm_error: float = 0.05      # retargeting: wrist / middle-knuckle distance to the human's
    max_tip_error: float = 0.08       # retargeting: fingertip distance to the human's (embodiment bias is expected)
    max_penetration: float = 0.003    # hand–arm overlap tolerated
    max_table_penetration: float = 0.006  # arm/palm–table overlap tolerated
    max_finger_table_penetration: float = 0.015  # finger–table overlap tolerated (grasping flat objects)


@dataclass(frozen=True)
class Rejection:
    """Why a reference was rejected: ``reason`` is one of :data:`REASONS`; ``frame`` the first bad one."""

    reason: str
    frame: int | None
    detail: str

    def as_dict(self) -> dict:
        return asdict(self)


#: ``no_grasp``: synthesis found no human grasp; ``no_planned_grasp``: no pinch planned for this hand fits
#: (builds with ``planned_grasp``, :mod:`adadex.data.planned_grasp`)
REASONS = ("no_grasp", "no_planned_grasp", "two_hands", "unreachable", "hand_arm_collision", "table_collision",
           "window_too_short")


class KinematicReplay:
    """Replays references on one object's scene model (see the module docstring)."""

    def __init__(self, object_name: str):
        self.model = _replay_model(object_name)
        self.data = mujoco.MjData(self.model)
        self._sites = [self.model.site(s).id for s in TRACKED_SITES]
        self._robot_geom = np.isin(self.model.geom_contype, (_ARM, _HAND))
        fingers = [self.model.body(f"{p}_bs").id for p in ("if", "mf", "rf", "th")]
        self._finger_geom = np.array([any(descends(self.model, b, f) for f in fingers)
                                      for b in self.model.geom_bodyid])

    def link_poses(self, ref: Reference) -> np.ndarray:
        """(T, 5, 7) tracked-link poses of the replay, read from MuJoCo."""
        out = np.empty((ref.num_frames, len(TRACKED_SITES), 7))
        for t in range(ref.num_frames):
            self._set(ref, t)
            mujoco.mj_kinematics(self.model, self.data)
            out[t, :, :3] = self.data.site_xpos[self._sites]
            for k, s in enumerate(self._sites):
                mujoco.mju_mat2Quat(out[t, k, 3:], self.data.site_xmat[s])
        out[..., 3:] *= np.where(out[..., 3:4] < 0, -1.0, 1.0)
        return out

    def collisions(self, ref: Reference, max_penetration: float = 0.003, max_table_penetration: float = 0.006,
                   max_finger_table_penetration: float = 0.015) -> Rejection | None:
        """First frame where the hand overlaps the arm, or the robot the table, by more than the tolerance."""
        for t in range(ref.num_frames):
            self._set(ref, t)
            mujoco.mj_fwdPosition(self.model, self.data)
            for c in self.data.contact[: self.data.ncon]:
                g1, g2 = c.geom
                self_contact = self._robot_geom[g1] and self._robot_geom[g2]
                finger = self._finger_geom[g1] or self._finger_geom[g2]
                tol = max_penetration if self_contact else (
                    max_finger_table_penetration if finger else max_table_penetration)
                if c.dist >= -tol:
                    continue
                names = f"{_geom_name(self.model, g1)} and {_geom_name(self.model, g2)}, {-c.dist * 1000:.1f} mm"
                if self_contact:
                    return Rejection("hand_arm_collision", t, f"hand and arm overlap at frame {t}: {names}")
                return Rejection("table_collision", t, f"the robot goes into the table at frame {t}: {names}")
        return None

    def _set(self, ref: Reference, t: int) -> None:
        self.data.qpos[:NUM_JOINTS] = ref.hand_joint_pos[t]
        self.data.qpos[OBJECT_QPOS] = ref.object_pose[t]


def _geom_name(model: mujoco.MjModel, g: int) -> str:
    return model.geom(g).name or f"geom {g} of body {model.body(model.geom_bodyid[g]).name}"


@functools.lru_cache(maxsize=32)
def _replay_model(object_name: str) -> mujoco.MjModel:
    """The scene with contacts for checking: hand↔arm, robot↔world; the object collides with nothing."""
    model = build_scene_model(object_name)
    palm = model.body("palm").id
    base = model.body("link_base").id
    obj = model.body(OBJECT_BODY).id
    for g in range(model.ngeom):
        b = model.geom_bodyid[g]
        if b == obj:
            model.geom_contype[g] = model.geom_conaffinity[g] = 0
        elif descends(model, b, palm):
            model.geom_contype[g], model.geom_conaffinity[g] = _HAND, _ARM | _WORLD
        elif descends(model, b, base):
            # The hand's mount on link6 is a parent–child pair, which MuJoCo filters.
            model.geom_contype[g], model.geom_conaffinity[g] = _ARM, _WORLD
        else:
            model.geom_contype[g], model.geom_conaffinity[g] = _WORLD, 0
    # The broad phase prunes body pairs by per-body masks compiled from the geoms': refresh them.
    model.body_contype[:] = 0
    model.body_conaffinity[:] = 0
    np.bitwise_or.at(model.body_contype, model.geom_bodyid, model.geom_contype)
    np.bitwise_or.at(model.body_conaffinity, model.geom_bodyid, model.geom_conaffinity)
    return model


def check(ref: Reference, *, retarget_palm_error: np.ndarray | None = None,
          retarget_tip_error: np.ndarray | None = None,
          config: FeasibilityConfig = FeasibilityConfig()) -> Rejection | None:
    """``None`` if ``ref`` is feasible, else the first :class:`Rejection` found.

    Checks, in order: reachability (retargeting errors per frame, when given), the episode window,
    hand–arm and robot–table collisions in the kinematic replay.
    """
    for err, limit, what in ((retarget_palm_error, config.max_palm_error, "wrist/palm"),
                             (retarget_tip_error, config.max_tip_error, "fingertips")):
        if err is not None:
            bad = np.flatnonzero(np.asarray(err) > limit)
            if bad.size:
                t = int(bad[0])
                return Rejection("unreachable", t, f"the robot's {what} miss the human's by {err[t] * 100:.1f} cm "
                                                   f"at frame {t} (limit {limit * 100:.1f} cm)")
    try:
        ref.window()
    except WindowTooShortError as e:
        return Rejection("window_too_short", None, str(e))
    return KinematicReplay(ref.object_name).collisions(
        ref, config.max_penetration, config.max_table_penetration, config.max_finger_table_penetration)
