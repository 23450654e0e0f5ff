import json

import mujoco
import numpy as np
import pytest

from adadex.sim.effects import EFFECT_NAMES, EffectError, get_effect
from adadex.sim.patch import ModelPatch, PatchError
from adadex.sim.robot import HOME_QPOS
from adadex.sim.scene import SUBSTEPS, build_scene_model

LIBRARY = ("damping", "coulomb_friction", "armature", "actuator_delay", "actuator_lag", "torque_limit",
           "kp_scale", "kd_scale", "payload_mass", "joint_spring", "encoder_offset", "backlash")


def test_library_vocabulary():
    assert set(EFFECT_NAMES) == set(LIBRARY)
    for name in LIBRARY:
        eff = get_effect(name)
        assert eff.__doc__ and "signature" in eff.__doc__.lower()
        lo, hi = eff.bounds(["arm_j2", "if_pip"])
        assert np.all(lo <= eff.absent_values()) and np.all(eff.absent_values() <= hi)
        nom = eff.nominal_values(["arm_j2", "if_pip"])
        assert np.all((lo <= nom) & (nom <= hi)) and not eff.is_absent(nom[0])


def _run(model, command, steps=24):
    """mj_step loop with a sinusoidal command on all joints; qpos trajectory."""
    d = mujoco.MjData(model)
    d.qpos[:22] = HOME_QPOS
    mujoco.mj_forward(model, d)
    out = []
    for t in range(steps):
        d.ctrl[:] = command(t)
        for _ in range(SUBSTEPS):
            mujoco.mj_step(model, d)
        out.append(d.qpos.copy())
    return np.array(out)


@pytest.mark.parametrize("name", LIBRARY)
def test_absent_value_is_bit_identical_and_present_value_is_not(name):
    command = lambda t: HOME_QPOS + 0.2 * np.sin(0.7 * t)  # noqa: E731
    joints = ["arm_j2", "arm_j5", "if_pip", "th_mcp"]
    eff = get_effect(name)
    nominal = _run(build_scene_model(None), command)
    absent = ModelPatch().with_effect(name, joints, eff.absent_values())
    assert np.array_equal(_run(absent.build_model(), command), nominal)
    present = ModelPatch().with_effect(name, joints, eff.nominal_values(joints))
    q = _run(present.build_model(), command)
    qpos = present.transform_measurement(q[None, :, :22])[0]
    cmd = np.array([command(t) for t in range(24)])[None]
    if eff.stage == "command":
        assert not np.array_equal(present.transform_command(cmd, 1 / 12), cmd)
    else:
        assert not np.array_equal(qpos, nominal[:, :22])


def test_patch_round_trip_and_atomic_save(tmp_path):
    patch = (ModelPatch()
             .with_effect("coulomb_friction", ["if_pip", "if_dip"], [0.05, 0.04])
             .with_effect("actuator_delay", ["arm_j1"], 0.02))
    path = patch.save(tmp_path / "patch.json")
    assert [p.name for p in tmp_path.iterdir()] == ["patch.json"]
    loaded = ModelPatch.load(path)
    assert loaded.to_dict() == patch.to_dict()
    assert json.loads(path.read_text())["effects"][0]["params"]["friction"] == [0.05, 0.04]
    m = loaded.build_model()
    assert m.dof_frictionloss[9] == pytest.approx(0.04 + 0.001)
    assert m.actuator_delay[0] == pytest.approx(0.02)


@pytest.mark.parametrize("entry, match", [
    ({"effect": "dampign", "joints": ["if_pip"]}, "did you mean damping"),
    ({"effect": "damping", "joints": ["if_pipp"]}, "unknown joint"),
    ({"effect": "damping", "joints": ["if_pip"], "params": {"damping": [-1.0]}}, "outside"),
    ({"effect": "damping", "joints": ["if_pip"], "params": {"damp": [1.0]}}, "unknown parameters"),
    ({"effect": "damping", "joints": ["if_pip", "if_dip"], "params": {"damping": [0.1, 0.2, 0.3]}}, "one value per joint|shape"),
    ({"effect": "kp_scale", "joints": ["arm_j1"], "params": {"scale": [float("nan")]}}, "non-finite"),
])
def test_bad_patches_are_rejected_with_the_entry_named(tmp_path, entry, match):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"version": 1, "effects": [entry]}))
    with pytest.raises(PatchError, match=match):
        ModelPatch.load(path)


def test_duplicate_effect_on_a_joint_and_unknown_effect():
    with pytest.raises(PatchError, match="twice"):
        ModelPatch().with_effect("damping", ["if_pip"], 0.1).with_effect("damping", ["if_pip"], 0.2)
    with pytest.raises(EffectError, match="known effects"):
        get_effect("stribeck")


# ------------------------------------------------------------------------------------------------
# Scale effects (domain randomization's robot physics), composition, the patched-scene cache

SCALES = ("mass_scale", "friction_scale", "damping_scale")


def test_scale_effects_are_effects_but_not_screened():
    from adadex.sim.effects import EFFECTS, SCALE_EFFECT_NAMES

    assert set(SCALE_EFFECT_NAMES) == set(SCALES) and set(EFFECTS) == set(LIBRARY) | set(SCALES)
    for name in SCALES:
        eff = get_effect(name)
        assert eff.__doc__ and "signature" in eff.__doc__.lower() and eff.stage == "model"
        assert eff.absent_values().tolist() == [1.0]


@pytest.mark.parametrize("name", SCALES)
def test_scale_effect_absent_is_bit_identical_and_present_is_not(name):
    command = lambda t: HOME_QPOS + 0.2 * np.sin(0.7 * t)  # noqa: E731
    joints = ["arm_j2", "arm_j5", "if_pip", "th_mcp"]
    eff = get_effect(name)
    nominal_model = build_scene_model(None)
    nominal = _run(nominal_model, command)
    assert np.array_equal(_run(ModelPatch().with_effect(name, joints, eff.absent_values()).build_model(), command),
                          nominal)
    # Mixed values with absent ones: the joints left at 1 keep their model values exactly.
    mixed = ModelPatch().with_effect(name, joints, [[1.0], [1.0], [1.3], [1.0]]).build_model()
    present = ModelPatch().with_effect(name, joints, eff.nominal_values(joints)).build_model()
    if name == "friction_scale":    # free motion never touches anything: the contact friction is what changes
        changed = np.flatnonzero(present.geom_friction[:, 0] != nominal_model.geom_friction[:, 0])
        assert changed.size
        assert np.allclose(present.geom_friction[changed, 0], 0.8 * nominal_model.geom_friction[changed, 0])
        assert set(present.geom_bodyid[changed]) >= {present.body("link2").id, present.body("link5").id}
    else:
        assert not np.array_equal(_run(present, command), nominal)
    if name == "mass_scale":
        pip = mixed.jnt_bodyid[mixed.joint("if_pip").id]
        assert mixed.body_mass[pip] == pytest.approx(1.3 * nominal_model.body_mass[pip])
        assert np.delete(mixed.body_mass, pip).tolist() == np.delete(nominal_model.body_mass, pip).tolist()


def test_links_a_joint_moves_include_the_bodies_welded_to_it():
    from adadex.sim.effects import link_bodies

    m = build_scene_model("box_00")
    names = [[m.body(b).name for b in bodies] for bodies in link_bodies(m, [5, 8])]
    assert names == [["link6", "palm"], [m.body(m.jnt_bodyid[8]).name]]


def test_scale_effects_compose_with_additive_ones_in_any_order():
    base = build_scene_model(None)
    pip = 8
    a = (ModelPatch().with_effect("damping", ["if_pip"], 0.2).with_effect("damping_scale", ["if_pip"], 2.0)
         .with_effect("payload_mass", ["if_pip"], 0.05).with_effect("mass_scale", ["if_pip"], 1.5)).build_model()
    b = (ModelPatch().with_effect("mass_scale", ["if_pip"], 1.5).with_effect("payload_mass", ["if_pip"], 0.05)
         .with_effect("damping_scale", ["if_pip"], 2.0).with_effect("damping", ["if_pip"], 0.2)).build_model()
    body = base.jnt_bodyid[pip]
    for m in (a, b):
        assert m.dof_damping[pip] == pytest.approx(2.0 * base.dof_damping[pip] + 0.2)
        assert m.actuator_biasprm[pip, 2] == pytest.approx(2.0 * base.actuator_biasprm[pip, 2])
        assert m.body_mass[body] == pytest.approx(1.5 * base.body_mass[body] + 0.05)
    assert np.array_equal(a.body_subtreemass, b.body_subtreemass)


def test_patched_scene_is_cached_on_content_and_bounded(tmp_path):
    from adadex.sim import patch as patch_mod
    from adadex.sim.patch import SCENE_CACHE_SIZE, patched_scene

    one = ModelPatch().with_effect("damping", ["if_pip"], 0.2).save(tmp_path / "one.json")
    two = ModelPatch.from_dict(json.loads(one.read_text()))
    assert patched_scene("box_00", ModelPatch.load(one)) is patched_scene("box_00", two)
    assert patched_scene("box_00", two) is not patched_scene("box_00", two.with_effect("damping", ["if_dip"], 0.1))
    # Sensor and command effects do not change the compiled model: they share the nominal one.
    assert patched_scene(None, ModelPatch().with_effect("encoder_offset", ["if_pip"], 0.01)) is patched_scene(None)
    assert patch_mod._compiled_scene.cache_info().maxsize == SCENE_CACHE_SIZE
    # build_model hands out a copy: editing it leaves the cached model alone.
    m = ModelPatch.load(one).build_model("box_00")
    m.dof_damping[8] = 99.0
    assert patched_scene("box_00", two).dof_damping[8] == pytest.approx(0.23)


def test_patch_intervals_round_trip_and_update(tmp_path):
    from adadex.sim.patch import EffectInstance

    e = EffectInstance("damping", ("if_pip", "if_dip"), [[0.2], [0.1]], ci95=[[[0.18, 0.22]], [[0.09, 0.12]]])
    path = ModelPatch((e,)).save(tmp_path / "p.json")
    assert json.loads(path.read_text())["effects"][0]["ci95"] == {"damping": [[0.18, 0.22], [0.09, 0.12]]}
    loaded = ModelPatch.load(path)
    assert np.array_equal(loaded.effects[0].ci95, e.ci95)
    with pytest.raises(PatchError, match="ci95"):
        EffectInstance("damping", ("if_pip",), [[0.2]], ci95=[[[0.3, 0.1]]])
    up = loaded.updated(ModelPatch().with_effect("damping", ["if_dip"], 0.3).with_effect("armature", ["if_pip"], 0.01))
    assert [(x.effect, x.joints) for x in up.effects] == [("damping", ("if_pip",)), ("damping", ("if_dip",)),
                                                        ("armature", ("if_pip",))]
    assert up.effects[0].ci95.tolist() == [[[0.18, 0.22]]] and up.effects[1].values[0, 0] == 0.3
