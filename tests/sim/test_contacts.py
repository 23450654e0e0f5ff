import mujoco
import pytest

from adadex.sim.contacts import body_contact_forces
from adadex.sim.scene import OBJECT_BODY, build_scene_model, home_state


@pytest.fixture(scope="module")
def resting():
    m = build_scene_model("cube_050")
    d = mujoco.MjData(m)
    d.qpos[:], d.ctrl[:] = home_state(m)
    for _ in range(240):
        mujoco.mj_step(m, d)
    return m, d


def test_a_resting_object_is_held_up_by_the_table_with_its_weight(resting):
    m, d = resting
    bid = m.body(OBJECT_BODY).id
    forces = body_contact_forces(m, d, OBJECT_BODY)
    weight = float(m.body_subtreemass[bid]) * -m.opt.gravity[2]
    assert set(forces) == {"table"}
    assert forces["table"] == pytest.approx(weight, rel=0.05)
    assert body_contact_forces(m, d, bid) == forces          # by id as by name


STACK = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <body name="bottom" pos="0 0 0.05"><freejoint/><geom name="bottom_box" type="box" size="0.05 0.05 0.05" mass="1"/></body>
    <body name="top" pos="0 0 0.15"><freejoint/><geom name="top_box" type="box" size="0.03 0.03 0.05" mass="0.5"/></body>
  </worldbody>
</mujoco>
"""


def test_forces_are_summed_per_touching_geom():
    m = mujoco.MjModel.from_xml_string(STACK)
    d = mujoco.MjData(m)
    for _ in range(1000):
        mujoco.mj_step(m, d)
    g = -m.opt.gravity[2]
    bottom = body_contact_forces(m, d, "bottom")       # several contact points per pair, summed
    assert set(bottom) == {"floor", "top_box"}
    assert bottom["floor"] == pytest.approx(1.5 * g, rel=0.02)
    assert bottom["top_box"] == pytest.approx(0.5 * g, rel=0.02)
    assert body_contact_forces(m, d, "top") == {"bottom_box": pytest.approx(0.5 * g, rel=0.02)}


def test_unknown_bodies_are_refused(resting):
    m, d = resting
    with pytest.raises(ValueError, match="'mug_handle' is not in the model"):
        body_contact_forces(m, d, "mug_handle")
    with pytest.raises(ValueError, match="out of range"):
        body_contact_forces(m, d, m.nbody)
