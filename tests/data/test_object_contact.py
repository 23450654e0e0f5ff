"""Object-aware retargeting: the hull distance, the hand's collision spheres against MuJoCo's own
geometry, and a synthesized grasp retargeted with and without the object, judged by MuJoCo's
collision detection (not by the distance the solver uses)."""

from functools import lru_cache

import mujoco
import numpy as np
import pytest
import torch

from adadex.data.object_contact import (
    PAD_GEOMS,
    TIP_GEOMS,
    ObjectContact,
    hand_collision_spheres,
    hand_object_overlap,
    hull_planes,
    signed_distance,
)
from adadex.data.retarget import _MATCHED, TABLE_CLEARANCE_POINTS, Retargeter
from adadex.data.synth import NoiseConfig, Synthesizer, make_instruction
from adadex.sim.robot import NUM_JOINTS, joint_limits, robot_mjcf_path


pytestmark = pytest.mark.usefixtures("one_torch_thread")   # tests/data/conftest.py


def test_hull_signed_distance_of_a_cube():
    planes = hull_planes("cube_050")
    assert np.allclose(np.linalg.norm(planes[:, :3], axis=1), 1.0)
    pts = np.array([[0.0, 0.0, 0.0], [0.04, 0.0, 0.0], [0.0, -0.02, 0.0], [0.0, 0.0, 0.03]])
    assert np.allclose(signed_distance(pts, planes), [-0.025, 0.015, -0.005, 0.005])


def test_contact_settings_are_checked():
    with pytest.raises(ValueError, match="squeeze"):
        ObjectContact(squeeze=-0.001)
    with pytest.raises(ValueError, match="reach"):
        ObjectContact(reach=0.0)
    assert np.allclose(ObjectContact().activation(np.array([0.0, 0.015, 0.05])), [1.0, 0.5, 0.0])


def test_hand_spheres_lie_inside_mujocos_hand_geoms():
    """At random joints, every sphere (placed by the retargeter's FK) lies within a hand geom of the
    MuJoCo model, and the four tip spheres are the fingertip geoms themselves."""
    spheres = hand_collision_spheres()
    assert [s.kind for s in spheres[:4]] == ["tip"] * 4 and {s.kind for s in spheres[4:]} == {"keep_out"}
    rt = Retargeter(contact=ObjectContact())
    model = mujoco.MjModel.from_xml_path(str(robot_mjcf_path()))
    data = mujoco.MjData(model)
    lim = joint_limits()
    q = np.random.default_rng(0).uniform(lim[:, 0], lim[:, 1], (3, NUM_JOINTS))
    pts, _ = rt._points_jacobian(torch.as_tensor(q))
    S = len(_MATCHED) + len(TABLE_CLEARANCE_POINTS)
    hand = [g for g in range(model.ngeom) if model.geom(g).name.startswith(("palm", "if_", "mf_", "rf_", "th_"))]
    for n in range(len(q)):
        data.qpos[:NUM_JOINTS] = q[n]
        mujoco.mj_kinematics(model, data)
        centres = pts[n, S:].numpy()
        for k, name in enumerate(TIP_GEOMS):
            assert np.linalg.norm(centres[k] - data.geom(name).xpos) < 1e-6
        for c, s in zip(centres, spheres):
            assert min(_inside_by(model, data, g, c, s.radius) for g in hand) < 1e-6, s


def _inside_by(model, data, g: int, centre: np.ndarray, radius: float) -> float:
    """How far a sphere sticks out of geom ``g`` (≤ 0: contained), for capsules, boxes, spheres."""
    local = data.geom_xmat[g].reshape(3, 3).T @ (centre - data.geom_xpos[g])
    size = model.geom_size[g]
    kind = model.geom_type[g]
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return np.linalg.norm(local) + radius - size[0]
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        axial = np.clip(local[2], -size[1], size[1])
        return np.linalg.norm(local - [0, 0, axial]) + radius - size[0]
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        return float((np.abs(local) + radius - size).max())
    return np.inf


@lru_cache(maxsize=1)
def _grasp_motion():
    instr = make_instruction("lift", "cube_050", seed=3)
    return Synthesizer(NoiseConfig.clean()).synthesize(instr, seed=5)


@lru_cache(maxsize=2)
def _retargeted(with_object: bool) -> np.ndarray:
    m = _grasp_motion()
    kw = dict(object_pose=m.object_pose, object_names="cube_050") if with_object else {}
    return Retargeter(retry_above=np.inf, contact=ObjectContact()).retarget(m.keypoints, **kw).joint_pos


def _hold_penetrations(q: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Over the hold, from MuJoCo's collision detection: the deepest overlap with the object of a
    hand geom off the distal links, of a distal link's pad (the capsule the tip sphere ends), and
    each fingertip sphere's median depth into it (m, negative = apart)."""
    m = _grasp_motion()
    hold = slice(m.phases["manipulate"], m.phases["release"])
    depth = hand_object_overlap(q[hold], m.object_pose[hold], "cube_050")
    worst = max(d.max() for n, d in depth.items() if n not in TIP_GEOMS + PAD_GEOMS)
    return worst, max(depth[n].max() for n in PAD_GEOMS), np.array([np.median(depth[n]) for n in TIP_GEOMS])


def test_retargeting_with_the_object_keeps_the_hand_out_and_the_fingertips_on_it():
    blind, aware = _hold_penetrations(_retargeted(False)), _hold_penetrations(_retargeted(True))
    squeeze = ObjectContact().squeeze
    assert blind[0] > 0.01                      # keypoints alone sink palm-side links into the cube
    assert aware[0] < 0.002                     # with the object: only the fingertips enter it,
    assert aware[1] < squeeze + 0.002           # their distal pads no deeper than the tips
    assert (np.abs(aware[2] - squeeze) < 0.002).all(), aware[2]   # every tip squeezes as asked


def test_object_inputs_are_checked():
    m = _grasp_motion()
    rt = Retargeter(contact=ObjectContact())
    kp = m.keypoints[:4]
    with pytest.raises(ValueError, match="give both or neither"):
        rt.retarget(kp, object_pose=m.object_pose[:4])
    with pytest.raises(ValueError, match=r"object_pose: expected shape \(4, 7\)"):
        rt.retarget(kp, object_pose=m.object_pose[:5], object_names="cube_050")
    bad = m.object_pose[:4].copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="object_pose: non-finite value in sequence 0 at frame 2"):
        rt.retarget(kp, object_pose=bad, object_names="cube_050")
    with pytest.raises(ValueError, match="object_names: expected one name or 2"):
        rt.retarget(np.stack([kp, kp]), object_pose=m.object_pose[:4], object_names=["cube_050"] * 3)
