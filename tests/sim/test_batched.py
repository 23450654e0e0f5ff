import mujoco
import numpy as np
import pytest

from adadex.sim import objects
from adadex.sim.batched import BatchedSim
from adadex.sim.robot import joint_limits
from adadex.sim.scene import SUBSTEPS, build_scene_model, build_scene_spec, home_state


@pytest.fixture(scope="module")
def model():
    return build_scene_model(objects.OBJECT_NAMES[0])


def _random_ctrls(model, steps, batch, seed):
    lim = joint_limits()
    rng = np.random.default_rng(seed)
    _, home = home_state(model)
    noise = rng.normal(0, 0.05, size=(steps, batch, 22))
    return np.clip(home + np.cumsum(noise, axis=0), lim[:, 0], lim[:, 1])


def _run(model, nthread, ctrls, qpos):
    sim = BatchedSim(model, ctrls.shape[1], nthread=nthread)
    sim.reset(qpos=qpos)
    for c in ctrls:
        out = sim.step(c)
    sim.close()
    return sim.state.copy(), out


def test_bit_identical_for_any_thread_count(model):
    qpos, _ = home_state(model)
    ctrls = _random_ctrls(model, 12, 6, seed=1)
    s0, _ = _run(model, 0, ctrls, qpos)
    s1, _ = _run(model, 1, ctrls, qpos)
    s2, out = _run(model, 2, ctrls, qpos)
    assert np.array_equal(s0, s1) and np.array_equal(s0, s2)
    # The worlds did move, differently from each other.
    assert not np.allclose(s0[0], s0[1])
    assert np.all(out.time == pytest.approx(12 * SUBSTEPS * model.opt.timestep))


def test_batched_equals_a_plain_mj_step_loop(model):
    """One world through BatchedSim follows the same physics as mj_step with the control held."""
    qpos, _ = home_state(model)
    ctrls = _random_ctrls(model, 4, 1, seed=2)
    sim = BatchedSim(model, 1, nthread=0)
    sim.reset(qpos=qpos)
    d = mujoco.MjData(model)
    d.qpos[:] = qpos
    mujoco.mj_forward(model, d)
    for c in ctrls:
        out = sim.step(c)
        d.ctrl[:] = c[0]
        d.qacc_warmstart[:] = 0  # the rollout starts every control step from a cold warmstart
        for _ in range(SUBSTEPS):
            mujoco.mj_step(model, d)
    np.testing.assert_allclose(out.joint_pos[0], d.qpos[:22], atol=1e-6)
    np.testing.assert_allclose(out.object_pose[0], d.qpos[22:29], atol=1e-6)
    np.testing.assert_allclose(out.link_pose[0, 0, :3], d.site("palm").xpos, atol=1e-6)


def test_readouts_shapes_and_quaternions(model):
    qpos, ctrl = home_state(model)
    sim = BatchedSim(model, 3, nthread=2)
    sim.reset(qpos=qpos)
    out = sim.step(np.tile(ctrl, (3, 1)))
    assert out.joint_pos.shape == (3, 22) and out.joint_vel.shape == (3, 22)
    assert out.link_pose.shape == (3, 5, 7) and out.object_pose.shape == (3, 7)
    np.testing.assert_allclose(np.linalg.norm(out.link_pose[..., 3:], axis=-1), 1.0, atol=1e-9)
    assert not out.unstable.any()


def test_partial_reset_touches_only_those_worlds(model):
    qpos, ctrl = home_state(model)
    sim = BatchedSim(model, 4, nthread=2)
    sim.reset(qpos=qpos)
    for c in _random_ctrls(model, 3, 4, seed=3):
        sim.step(c)
    before = sim.state.copy()
    out = sim.reset(qpos=qpos, worlds=[1, 3])
    assert np.array_equal(sim.state[[0, 2]], before[[0, 2]])
    np.testing.assert_allclose(out.joint_pos[[1, 3]], np.tile(qpos[:22], (2, 1)))
    assert np.all(out.time[[1, 3]] == 0)
    with pytest.raises(IndexError):
        sim.reset(worlds=[4])


def test_per_world_models_change_the_physics(model):
    heavy_spec = build_scene_spec(objects.OBJECT_NAMES[0])
    heavy = heavy_spec.compile()
    heavy.body_mass[heavy.body("palm").id] += 1.0   # a 1 kg payload in the hand
    qpos, ctrl = home_state(model)
    sim = BatchedSim([model, heavy], nthread=2)
    sim.reset(qpos=qpos)
    for _ in range(36):
        out = sim.step(np.tile(ctrl, (2, 1)))
    # At steady state the loaded arm sags further under the same PD gains.
    assert abs(out.joint_pos[1, 1] - ctrl[1]) > abs(out.joint_pos[0, 1] - ctrl[1]) + 1e-4


def test_bad_inputs_raise(model):
    other = build_scene_model(objects.OBJECT_NAMES[-1])
    if other.signature != model.signature:
        with pytest.raises(ValueError, match="structure"):
            BatchedSim([model, other])
    with pytest.raises(ValueError, match="batch_size"):
        BatchedSim(model)
    sim = BatchedSim(model, 2)
    with pytest.raises(ValueError, match="ctrl must have shape"):
        sim.step(np.zeros((3, 22)))


def diverging_model(spec):
    """The scene of ``spec`` with absurd, unlimited servo stiffness and no armature: it diverges at this
    timestep (the unstable world of the backends' tests)."""
    wild = spec.compile()
    wild.actuator_gainprm[:, 0] *= 1e4
    wild.actuator_biasprm[:, 1] *= 1e4
    wild.actuator_forcerange[:] *= 1e4
    wild.jnt_actfrcrange[:] *= 1e4
    wild.dof_armature[:] = 0
    return wild


def test_unstable_world_is_flagged_and_others_continue():
    spec = build_scene_spec(objects.OBJECT_NAMES[0])
    stable = spec.compile()
    wild = diverging_model(spec)
    qpos, ctrl = home_state(stable)
    sim = BatchedSim([stable, wild], nthread=2)
    sim.reset(qpos=qpos)
    flagged = np.zeros(2, bool)
    target = ctrl.copy()
    target[:6] += 0.5
    for _ in range(6):
        flagged |= sim.step(np.tile(target, (2, 1))).unstable
    assert flagged.tolist() == [False, True]


def test_worlds_with_different_objects_step_together():
    """Uniform-layout scenes of different objects share one structure; each world keeps its own
    object's geometry and mass in the single rollout call."""
    from adadex.sim import objects
    from adadex.sim.scene import OBJECT_QPOS, build_scene_model, home_state

    names = ["cube_050", "torus_00", "mug_00", "sphere_03"]       # 1, 16, 21 and 1 parts
    models = [build_scene_model(n, uniform_layout=True) for n in names]
    assert len({m.signature for m in models}) == 1 and len({m.ngeom for m in models}) == 1
    plain = build_scene_model("torus_00")
    assert abs(models[1].body("object").mass[0] - plain.body("object").mass[0]) <= 1.1e-6   # the 1 mg placeholder
    sim = BatchedSim(models, nthread=2)
    qpos = np.stack([home_state(m)[0] for m in models])
    qpos[:, OBJECT_QPOS.start + 2] += 0.02                          # drop each object from 2 cm
    out = None
    for w, q in enumerate(qpos):
        sim.reset(qpos=q, worlds=[w])
    for _ in range(24):                                             # 2 s
        out = sim.step(np.stack([home_state(m)[1] for m in models]))
    assert not out.unstable.any()
    rest = out.object_pose[:, 2]
    expected = np.array([objects.get_object(n).half_height for n in names])
    assert np.abs(rest - expected).max() < 3e-3, (rest, expected)   # each on its own bottom, not the cube's


def test_max_object_parts_matches_the_registry():
    from adadex.sim import objects

    assert objects.MAX_OBJECT_PARTS == max(len(objects.get_object(n).parts()) for n in objects.OBJECT_NAMES)
    import mujoco
    spec = mujoco.MjSpec()
    with pytest.raises(ValueError, match="less than the 16 parts"):
        objects.add_object_geoms(spec, spec.worldbody.add_body(name="o"), "torus_00", pad_to=2)


def test_set_models_swaps_a_worlds_object():
    from adadex.sim.scene import OBJECT_QPOS

    names = ["torus_00", "cube_050"]
    models = [build_scene_model(n, uniform_layout=True) for n in names]
    sim = BatchedSim([models[0], models[0]], nthread=2)
    mug = build_scene_model("mug_00", uniform_layout=True)
    sim.set_models([1], [mug])                       # world 1 now holds the mug
    assert sim.models[1] is mug and sim.models[0] is models[0]
    q = home_state(mug)[0]
    q[OBJECT_QPOS.start + 2] += 0.02
    sim.reset(qpos=q, worlds=[1])
    for _ in range(24):
        out = sim.step(np.stack([home_state(m)[1] for m in sim.models]))
    assert not out.unstable.any()
    assert abs(out.object_pose[1, 2] - objects.get_object("mug_00").half_height) < 3e-3
    with pytest.raises(ValueError, match="uniform_layout"):
        sim.set_models([0], [build_scene_model("cube_050")])
    with pytest.raises(IndexError):
        sim.set_models([2], [mug])


def test_every_object_has_the_same_uniform_structure():
    """All 80 uniform-layout scenes share one structure, down to the sparse inertia size."""
    keys = {(m.signature, m.nC, m.ngeom, m.nmesh)
            for m in (build_scene_model(n, uniform_layout=True) for n in objects.OBJECT_NAMES)}
    assert len(keys) == 1, keys


@pytest.mark.parametrize("effect, params", [("actuator_delay", {"delay": 0.08}), ("actuator_lag", {"tau": 0.06})])
def test_a_delayed_or_lagged_servo_reset_with_its_command_holds_its_pose(effect, params):
    """A reset with ``ctrl`` fills the delay's history buffer and the lag's activation with that command,
    as on a robot that has been holding its pose; without it they start at 0 rad and the joints jolt."""
    from adadex.sim.patch import ModelPatch, patched_scene

    patch = ModelPatch.from_dict({"version": 1, "model": "builtin", "effects": [
        {"effect": effect, "joints": ["arm_j2", "arm_j3", "if_pip"], "params": params}]})
    model = patched_scene(objects.OBJECT_NAMES[0], patch)
    qpos, home = home_state(model)
    moved = {}
    for held in (True, False):
        sim = BatchedSim(model, 2, nthread=0)
        sim.reset(qpos=qpos, ctrl=home if held else None)
        q0 = sim.readout().joint_pos.copy()
        moved[held] = np.abs(sim.step(np.tile(home, (2, 1))).joint_pos - q0).max()
        sim.close()
    assert moved[True] < 0.01 < moved[False], moved
