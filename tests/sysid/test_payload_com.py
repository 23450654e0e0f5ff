"""``payload_mass`` is a point mass at the combined centre of mass of the link the joint moves (issue 43):
the joint's body and the bodies welded to it (on arm_j6, link6 and the palm). The link keeps its centre
of mass and its inertia about it and gains the mass; the body that carries it gets a new mass, centre
of mass and principal inertia (a proper rotation); 0 kg is the snapshot's model bit for bit, and
repeated applications with other values never accumulate."""

import copy

import mujoco
import numpy as np
import pytest

from adadex.errors import AdadexError
from adadex.geometry import rotation
from adadex.sim.effects import ModelBase, get_effect, link_bodies, robot_ids
from adadex.sim.patch import ModelPatch, patched_scene
from adadex.sim.robot import JOINT_NAMES

#: A link of two bodies (link6 + palm), a forearm and a fingertip of one body each.
JOINTS = ["arm_j6", "arm_j4", "if_dip"]
FIELDS = ("body_mass", "body_ipos", "body_iquat", "body_inertia", "body_subtreemass", "body_invweight0",
          "dof_invweight0", "actuator_acc0")


@pytest.fixture(scope="module")
def nominal():
    return patched_scene(None, ModelPatch())


def _link(m, joint):
    return link_bodies(m, robot_ids(m, [JOINT_NAMES.index(joint)])[0])[0]


def _link_mass_com_inertia(m, joint):
    """(mass, centre of mass, inertia tensor about it), world frame, at the model's qpos0."""
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    bodies = _link(m, joint)
    mass = m.body_mass[bodies].sum()
    com = (m.body_mass[bodies, None] * d.xipos[bodies]).sum(0) / mass
    inertia = np.zeros((3, 3))
    for b in bodies:
        R, r = d.ximat[b].reshape(3, 3), d.xipos[b] - com
        inertia += (R * m.body_inertia[b]) @ R.T + m.body_mass[b] * (r @ r * np.eye(3) - np.outer(r, r))
    return mass, com, inertia


def _apply(m, base, joints, masses):
    get_effect("payload_mass").apply_model(m, base, np.array([JOINT_NAMES.index(j) for j in joints]),
                                           np.asarray(masses, dtype=float).reshape(-1, 1))


@pytest.mark.parametrize("joint", JOINTS)
def test_the_payload_sits_at_the_links_centre_of_mass(nominal, joint):
    mp = 0.6 if joint.startswith("arm") else 0.05
    m = ModelPatch().with_effect("payload_mass", [joint], mp).build_model()
    mass0, com0, inertia0 = _link_mass_com_inertia(nominal, joint)
    mass1, com1, inertia1 = _link_mass_com_inertia(m, joint)
    assert mass1 == pytest.approx(mass0 + mp, rel=1e-12)
    # the mass-weighted combination of the link and a point at its old centre of mass: the same point
    np.testing.assert_allclose(com1, (mass0 * com0 + mp * com0) / (mass0 + mp), atol=1e-12)
    # a point mass at the centre of mass adds nothing to the inertia about it (parallel-axis terms)
    np.testing.assert_allclose(inertia1, inertia0, rtol=0, atol=1e-12 * np.abs(inertia0).max())
    # only the joint's own body changed; the welded ones keep their values
    body = m.jnt_bodyid[m.joint(joint).id]
    for f in ("body_mass", "body_ipos", "body_iquat", "body_inertia"):
        a, b = getattr(m, f), getattr(nominal, f)
        others = np.arange(m.nbody) != body
        assert np.array_equal(a[others], b[others]), f
    # the gravity torques see the mass: the subtree masses above the link grew by it
    parent = m.body_parentid[body]
    assert m.body_subtreemass[parent] == pytest.approx(nominal.body_subtreemass[parent] + mp)


def test_the_carrying_bodys_inertia_is_a_proper_principal_frame(nominal):
    """link6 carries the mass 4.3 cm from its own centre of mass: its frame turns, its inertia stays a
    symmetric positive definite tensor equal to the parallel-axis sum, its quaternion a unit rotation."""
    m = ModelPatch().with_effect("payload_mass", ["arm_j6"], 0.6).build_model()
    b, palm = m.body("link6").id, m.body("palm").id
    assert nominal.body_pos[palm].tolist() == [0, 0, 0] and nominal.body_quat[palm].tolist() == [1, 0, 0, 0]
    m0, c0 = nominal.body_mass[b], nominal.body_ipos[b]
    mp = 0.6
    link = (m0 * c0 + nominal.body_mass[palm] * nominal.body_ipos[palm]) / (m0 + nominal.body_mass[palm])
    com = (m0 * c0 + mp * link) / (m0 + mp)
    np.testing.assert_allclose(m.body_ipos[b], com, atol=1e-15)
    assert m.body_mass[b] == pytest.approx(m0 + mp, rel=1e-15)

    def tensor(model):
        R = rotation(model.body_iquat[b]).as_matrix()
        return (R * model.body_inertia[b]) @ R.T

    def point(r):
        return r @ r * np.eye(3) - np.outer(r, r)

    expected = tensor(nominal) + m0 * point(c0 - com) + mp * point(link - com)
    got = tensor(m)
    np.testing.assert_allclose(got, expected, atol=1e-15)
    np.testing.assert_allclose(got, got.T, atol=0)
    assert np.all(np.linalg.eigvalsh(got) > 0) and np.all(m.body_inertia[b] > 0)
    i1, i2, i3 = np.sort(m.body_inertia[b])       # principal moments of a rigid body: triangle inequality
    assert i1 + i2 >= i3 * (1 - 1e-12)
    assert np.linalg.norm(m.body_iquat[b]) == pytest.approx(1.0, abs=1e-12)
    assert np.linalg.det(rotation(m.body_iquat[b]).as_matrix()) == pytest.approx(1.0, abs=1e-12)
    assert not np.allclose(m.body_iquat[b], nominal.body_iquat[b])   # the frame did turn


def test_zero_is_the_base_model_and_values_never_accumulate(nominal):
    m = copy.copy(nominal)
    base = ModelBase.of(m)
    _apply(m, base, JOINTS, [0.6, 1.0, 0.05])
    once = {f: getattr(m, f).copy() for f in FIELDS}
    _apply(m, base, JOINTS, [2.0, 0.1, 0.2])
    _apply(m, base, JOINTS, [0.6, 1.0, 0.05])
    for f in FIELDS:
        assert np.array_equal(getattr(m, f), once[f]), f
    _apply(m, base, JOINTS, [0.0, 0.0, 0.0])
    for f in FIELDS:
        assert np.array_equal(getattr(m, f), getattr(nominal, f)), f
    # mixed: a joint at 0 keeps its body exactly, the others carry their mass
    _apply(m, base, JOINTS, [0.0, 1.0, 0.0])
    for j in ("arm_j6", "if_dip"):
        b = m.jnt_bodyid[m.joint(j).id]
        for f in FIELDS[:4]:
            assert np.array_equal(getattr(m, f)[b], getattr(nominal, f)[b]), (j, f)
    # and the base restores everything the payload touched
    base.restore(m)
    for f in FIELDS:
        assert np.array_equal(getattr(m, f), getattr(nominal, f)), f


def test_a_payload_adds_to_the_scaled_link_at_its_centre_of_mass(nominal):
    """mass_scale's docstring: a payload adds to the scaled mass (in either order in the patch)."""
    a = (ModelPatch().with_effect("payload_mass", ["arm_j6"], 0.6).with_effect("mass_scale", ["arm_j6"], 1.5)
         ).build_model()
    b = (ModelPatch().with_effect("mass_scale", ["arm_j6"], 1.5).with_effect("payload_mass", ["arm_j6"], 0.6)
         ).build_model()
    scaled = ModelPatch().with_effect("mass_scale", ["arm_j6"], 1.5).build_model()
    body = nominal.body("link6").id
    for m in (a, b):
        assert m.body_mass[body] == pytest.approx(1.5 * nominal.body_mass[body] + 0.6, rel=1e-14)
        mass1, com1, inertia1 = _link_mass_com_inertia(m, "arm_j6")
        mass0, com0, inertia0 = _link_mass_com_inertia(scaled, "arm_j6")
        assert mass1 == pytest.approx(mass0 + 0.6, rel=1e-14)
        np.testing.assert_allclose(com1, com0, atol=1e-12)
        np.testing.assert_allclose(inertia1, inertia0, rtol=0, atol=1e-12 * np.abs(inertia0).max())
    for f in FIELDS:
        assert np.array_equal(getattr(a, f), getattr(b, f)), f


def test_a_payload_that_leaves_no_mass_is_refused_naming_the_field(nominal):
    m = copy.copy(nominal)
    with pytest.raises(AdadexError, match=r"payload_mass: mass=-2 kg on body 'link6'"):
        _apply(m, ModelBase.of(m), ["arm_j6"], [-2.0])
