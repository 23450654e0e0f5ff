"""What retargeting needs to know about the object: its convex hull and the hand's collision volumes.

Keypoint retargeting alone is blind to the object: the robot's fingers, longer than a human's and
with a shorter palm, end up wherever the scaled human keypoints put them — in the ``small``
dataset built without this module, 5–35 mm inside the object during the hold (finger pads, bases
and the thumb's proximal link as well as the tips). :class:`ObjectContact` adds two terms to the
retargeting solve (``Retargeter(contact=ObjectContact())``, ``adadex data build --contact``):

* **keep out**: every hand collision volume but the fingertip spheres stays outside the object's
  convex hull (what MuJoCo collides with);
* **fingertip contact**: while the human fingertip is within ``reach`` of the object's surface, the
  robot's fingertip sphere goes to where the human's touches (the human tip's nearest hull face),
  ``squeeze`` deep along that face's normal, so the position servos press (as
  :func:`adadex.sim.grasp.scripted_grasp_lift` plans its pinch).

Hand volumes are read from the robot's MJCF (:func:`hand_collision_spheres`): a capsule becomes
spheres along its axis, a box spheres on a grid, each in the frame of the pytorch-kinematics chain
link that carries it. Distances use the hull's face planes (:func:`hull_planes`): the largest
plane distance is the exact depth inside and a lower bound outside, which is all the two terms need.

:func:`hand_object_overlap` measures the result with MuJoCo's own collision detection: how deep
each hand geom of a reference sits inside the object, frame by frame.

Example
-------
>>> from adadex.data.object_contact import hand_collision_spheres, hull_planes
>>> planes = hull_planes("cube_050")
>>> planes.shape                      # a cube: six faces, (normal, offset)
(6, 4)
>>> spheres = hand_collision_spheres()
>>> sorted({s.kind for s in spheres})
['keep_out', 'tip']
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import mujoco
import numpy as np
from scipy.spatial import ConvexHull

from adadex.errors import ArrayError, ConfigError, check_numbers
from adadex.sim.objects import get_object
from adadex.sim.robot import NUM_JOINTS, robot_mjcf_path
from adadex.sim.scene import OBJECT_BODY, OBJECT_QPOS, build_scene_model, descends

#: Fingertip spheres in the order of the human tips they follow (thumb, index, middle, ring).
TIP_GEOMS = ("th_tip_col", "if_tip_col", "mf_tip_col", "rf_tip_col")
#: The distal phalanges' capsules (the pads the tip spheres end), in the same order.
PAD_GEOMS = ("th_ds_col", "if_ds_col", "mf_ds_col", "rf_ds_col")


@dataclass(frozen=True)
class ObjectContact:
    """Weights and distances of the object terms in retargeting (lengths in m).

    ``keep_out``: weight of a hand volume's depth inside the object. ``contact``: weight of a
    fingertip's distance from its contact depth. ``squeeze``: how deep the fingertip sphere is put
    into the object while in contact (the servos' grip comes from it). ``reach``: a human fingertip
    nearer the surface than this is in contact (the weight ramps to full over the last
    ``reach / 2``). ``damping``: initial Levenberg damping of the solve while these terms are on
    (their hinges and changes of nearest face make undamped Gauss–Newton steps overshoot);
    ``iters``: iterations per frame then (at least the retargeter's own).
    """

    keep_out: float = 10.0
    contact: float = 3.0
    squeeze: float = 0.006
    reach: float = 0.02
    damping: float = 1e-3
    iters: int = 8

    def __post_init__(self):
        check_numbers("ObjectContact", self, asdict(self))
        for name in ("keep_out", "contact", "squeeze", "damping"):
            if getattr(self, name) < 0:
                raise ConfigError(f"ObjectContact.{name} must be ≥ 0, got {getattr(self, name)}")
        if self.iters < 1:
            raise ConfigError(f"ObjectContact.iters must be ≥ 1, got {self.iters}")
        if not self.reach > 0:
            raise ConfigError(f"ObjectContact.reach must be > 0, got {self.reach}")

    def activation(self, human_tip_distance: np.ndarray) -> np.ndarray:
        """Contact weight in [0, 1] from a human fingertip's distance to the surface."""
        return np.clip((self.reach - np.asarray(human_tip_distance)) / (0.5 * self.reach), 0.0, 1.0)


@functools.lru_cache(maxsize=None)
def hull_planes(object_name: str) -> np.ndarray:
    """(F, 4) outward unit normals and offsets of the object's convex hull faces in its own frame:
    a point ``p`` is ``n·p + d`` from face ``(n, d)``, the largest over faces is its signed distance."""
    eq = ConvexHull(np.asarray(get_object(object_name).mesh().vertices)).equations
    return np.unique(np.round(eq, 9), axis=0)


def signed_distance(points: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(…,) signed distance of (…, 3) points (object frame) to a hull of ``planes``; < 0 inside."""
    return (np.asarray(points) @ planes[:, :3].T + planes[:, 3]).max(-1)


@dataclass(frozen=True)
class HandSphere:
    """A sphere of a hand collision volume: chain ``frame``, ``offset`` in it, ``radius``, ``kind``."""

    frame: str
    offset: tuple[float, float, float]
    radius: float
    kind: str           # "tip" (one per finger, :data:`TIP_GEOMS` order) or "keep_out"


@functools.lru_cache(maxsize=1)
def hand_collision_spheres() -> tuple[HandSphere, ...]:
    """The hand's collision geoms as spheres in chain-link frames (see the module docstring).

    A distal capsule's end under the fingertip sphere is left out: the tip sphere covers it and
    must be allowed into the object.
    """
    from adadex.sim.kinematics import RobotKinematics

    model = mujoco.MjModel.from_xml_path(str(robot_mjcf_path()))
    chain_frames = set(RobotKinematics().chain.get_frame_names())
    tips, out = {}, []
    for g in _hand_geoms(model):
        frame, pose = _in_chain_frame(model, int(model.geom_bodyid[g]), chain_frames)
        local = _geom_spheres(model, g)
        for centre, radius in local:
            p = pose[:3, :3] @ centre + pose[:3, 3]
            name = model.geom(g).name
            if name in TIP_GEOMS:
                tips[name] = HandSphere(frame, tuple(p), float(radius), "tip")
            else:
                out.append((name, HandSphere(frame, tuple(p), float(radius), "keep_out")))
    missing = [t for t in TIP_GEOMS if t not in tips]
    if missing:
        raise ValueError(f"{robot_mjcf_path()} lacks fingertip geoms {missing}")
    kept = []
    for name, s in out:   # drop keep-out spheres that overlap their own finger's tip sphere
        tip = next((t for t in tips.values() if t.frame == s.frame), None)
        if tip is not None and np.linalg.norm(np.subtract(s.offset, tip.offset)) < tip.radius + s.radius - 0.004:
            continue
        kept.append(s)
    return tuple(tips[t] for t in TIP_GEOMS) + tuple(kept)


def hand_object_overlap(joint_pos: np.ndarray, object_pose: np.ndarray, object_name: str, *,
                        margin: float = 0.05) -> dict[str, np.ndarray]:
    """Per hand collision geom (by name), its depth inside the object at each frame (T,), m, from
    MuJoCo's collision detection on the scene posed kinematically; negative = apart (down to
    ``-margin``: geoms farther away read ``-margin``).

    ``joint_pos`` (T, 22) and ``object_pose`` (T, 7) are a reference's (``ref.hand_joint_pos``,
    ``ref.object_pose``).
    """
    q, pose = np.asarray(joint_pos, float), np.asarray(object_pose, float)
    if q.ndim != 2 or q.shape[1] != NUM_JOINTS or pose.shape != (len(q), 7):
        raise ArrayError(f"expected joint_pos (T, {NUM_JOINTS}) and object_pose (T, 7), got {q.shape} and {pose.shape}")
    model = build_scene_model(object_name)
    model.geom_margin[:] = margin
    data = mujoco.MjData(model)
    obj = model.body(OBJECT_BODY).id
    hand = _hand_geoms(model)
    depth = np.full((len(hand), len(q)), -margin)
    row = {g: k for k, g in enumerate(hand)}
    for t in range(len(q)):
        data.qpos[:NUM_JOINTS] = q[t]
        data.qpos[OBJECT_QPOS] = pose[t]
        mujoco.mj_fwdPosition(model, data)
        for c in data.contact[: data.ncon]:
            g1, g2 = c.geom
            other = g2 if model.geom_bodyid[g1] == obj else g1 if model.geom_bodyid[g2] == obj else None
            if other in row:
                depth[row[other], t] = max(depth[row[other], t], -c.dist)
    return {model.geom(g).name: depth[k] for k, g in enumerate(hand)}


def _hand_geoms(model) -> list[int]:
    """The colliding geoms of the hand (the palm body and everything below it)."""
    palm = model.body("palm").id
    return [g for g in range(model.ngeom) if model.geom_contype[g] and descends(model, int(model.geom_bodyid[g]), palm)]


def _in_chain_frame(model, body: int, chain_frames: set) -> tuple[str, np.ndarray]:
    """The nearest chain link at or above ``body`` and ``body``'s pose in it (4×4)."""
    pose = np.eye(4)
    while model.body(body).name not in chain_frames:
        local = np.eye(4)
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, model.body_quat[body])
        local[:3, :3], local[:3, 3] = rot.reshape(3, 3), model.body_pos[body]
        pose = local @ pose
        body = int(model.body_parentid[body])
        if body == 0:
            raise ValueError("a hand geom's body is not below any kinematic-chain link")
    return model.body(body).name, pose


def _geom_spheres(model, g: int) -> list[tuple[np.ndarray, float]]:
    """Spheres (centre in the body frame, radius) covering geom ``g``: capsule, box or sphere."""
    rot = np.empty(9)
    mujoco.mju_quat2Mat(rot, model.geom_quat[g])
    rot, pos, size = rot.reshape(3, 3), model.geom_pos[g], model.geom_size[g]
    kind = model.geom_type[g]
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return [(pos.copy(), float(size[0]))]
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        r, h = float(size[0]), float(size[1])
        n = max(2, int(np.ceil(2 * h / r)) + 1)
        return [(pos + rot[:, 2] * s, r) for s in np.linspace(-h, h, n)]
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        r = float(size.min())
        axes = [np.linspace(-(e - r), e - r, max(1, int(np.ceil((e - r) / r)) + 1)) for e in size]
        return [(pos + rot @ np.array([x, y, z]), r) for x in axes[0] for y in axes[1] for z in axes[2]]
    return []   # cylinders and meshes on the hand: none in this robot
