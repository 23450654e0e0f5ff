"""The workbench on a robot that is not adadex's (``--model``), and the exported built-in world."""

import json

import numpy as np
import pytest

from adadex.cli import main
from adadex.data.recording import load_recording
from adadex.sim.effects import get_effect
from adadex.sim.model_source import ModelSource, export_world
from adadex.sim.patch import ModelPatch, PatchError
from adadex.sysid.excite import design_excitation
from adadex.sysid.replay import Replayer
from tests.sysid.user_model import write_tiny_arm


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    return write_tiny_arm(tmp_path_factory.mktemp("model"))


def test_effects_are_sized_to_the_model(arm):
    robot = ModelSource(arm).robot()
    assert robot.names == ("shoulder", "elbow", "finger")
    np.testing.assert_allclose(robot.kp, [300, 120, 3])
    # Damping bounds follow each servo's kv (built-in finger: kv 0.25 → 0.6; this finger kv 0.1 → 0.24)
    hi = get_effect("damping").bounds(robot.names, robot)[1][:, 0]
    np.testing.assert_allclose(hi, [15.0 * 20 / 25, 15.0 * 8 / 25, 0.6 * 0.1 / 0.25])
    # friction scales with kp: the 3 N·m/rad finger gets half the built-in finger's bound
    assert get_effect("coulomb_friction").bounds(["finger"], robot)[1][0, 0] == pytest.approx(0.2)
    # the built-in robot keeps its tuned tables
    builtin = ModelSource().robot()
    assert get_effect("damping").bounds(["if_pip"], builtin)[1][0, 0] == get_effect("damping").bounds(["if_pip"])[1][0, 0]
    with pytest.raises(Exception, match="servoed joints of tiny_arm.xml"):
        get_effect("damping").bounds(["if_pip"], robot)


def test_the_loop_on_a_user_model_finds_the_effect_and_the_patch_remembers_the_model(arm, tmp_path, capsys):
    d = tmp_path
    robot = ModelSource(arm).robot()
    truth = ModelPatch(robot=robot).with_effect("coulomb_friction", ["finger"], 0.05)
    truth.save(d / "truth.json")
    m = ["--model", str(arm)]
    assert main(["sysid", "excite", "--joints", "finger", "--freqs", "0.5,2", "--amps", "0.3,1",
                 "--kinds", "sine,chirp", "--duration", "2", "--out", str(d / "plan.npz"), *m]) == 0
    assert main(["sysid", "simulate", str(d / "plan.npz"), "--patch", str(d / "truth.json"),
                 "--noise", "2e-4", "--seed", "1", "--out", str(d / "rec.npz"), *m]) == 0
    rec = load_recording(d / "rec.npz", robot=robot)
    assert rec.initial_qpos.shape == (rec.num_sequences, 3)
    assert main(["sysid", "diagnose", str(d / "rec.npz"), "--out", str(d / "D"), *m]) == 0
    diag = json.loads((d / "D" / "diagnosis.json").read_text())
    assert diag["verdict"] == "explained" and diag["model"] == robot.model_id
    assert diag["selected"][0]["effect"] == "coulomb_friction"
    assert diag["selected"][0]["params"]["friction"][0] == pytest.approx(0.05, rel=0.15)

    assert main(["sysid", "fit", str(d / "rec.npz"), "--accept", str(d / "D"), "--out", str(d / "patch.json"), *m]) == 0
    saved = json.loads((d / "patch.json").read_text())
    assert saved["model"] == robot.model_id
    patch = ModelPatch.load(d / "patch.json", robot=robot)
    rep = Replayer(rec)
    before = np.sqrt(((rep.simulate() - rec.joint_pos) ** 2).mean())
    after = np.sqrt(((rep.simulate(patch) - rec.joint_pos) ** 2).mean())
    assert after < 0.3 * before
    assert main(["sysid", "report", str(d / "rec.npz"), "--patch", str(d / "patch.json"),
                 "--out", str(d / "report.html"), *m]) == 0

    # the patch refuses another model: the built-in one, from the API and from the command line
    with pytest.raises(PatchError, match="fitted on model tiny_arm.xml"):
        ModelPatch.load(d / "patch.json")
    assert main(["sysid", "excite", "--joints", "if_dip", "--freqs", "1", "--amps", "1", "--kinds", "sine",
                 "--poses", "loaded", "--duration", "1", "--out", str(d / "builtin.npz")]) == 0
    capsys.readouterr()
    assert main(["sysid", "compare", str(d / "builtin.npz"), "--patch", str(d / "patch.json")]) == 2
    assert "fitted on model tiny_arm.xml" in capsys.readouterr().err
    # and the user's recording is not read as one of the built-in robot
    assert main(["sysid", "compare", str(d / "rec.npz")]) == 2
    assert "initial_qpos" in capsys.readouterr().err


def test_exported_world_replays_exactly_as_the_builtin_scene(tmp_path):
    path = export_world(tmp_path / "world.xml")
    assert main(["sim", "export", "--out", str(tmp_path / "world2.xml")]) == 0
    assert (tmp_path / "world2.xml").read_text() == path.read_text()
    plan = design_excitation(["arm_j2", "if_pip"], freqs=(1.5,), amps=(1.0,), kinds=("sine",), duration=1.0)
    rec = plan.to_recording(plan.command.copy())
    src = ModelSource(path)
    np.testing.assert_array_equal(Replayer(rec).simulate(full=True), Replayer(rec, model=src).simulate(full=True))
    effects = [("actuator_delay", ["if_pip"], 0.03), ("kp_scale", ["arm_j2"], 0.6), ("payload_mass", ["arm_j2"], 1.0)]
    ours, theirs = ModelPatch(), ModelPatch(robot=src.robot())
    for e in effects:
        ours, theirs = ours.with_effect(*e), theirs.with_effect(*e)
    np.testing.assert_array_equal(Replayer(rec).simulate(ours), Replayer(rec, model=src).simulate(theirs))
