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
