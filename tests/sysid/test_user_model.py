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
    assert "rec.npz: joint_names[" in capsys.readouterr().err     # the user's joints, named


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


def _loop_files(arm, d, truth: ModelPatch, joints, **excite):
    """excite + simulate on ``arm`` (short: 2 s sequences), ``truth`` hidden in the recording."""
    truth.save(d / "truth.json")
    m = ["--model", str(arm)]
    opts = {"--freqs": "0.5,2", "--amps": "0.3,1", "--kinds": "sine,chirp", "--duration": "2", **excite}
    assert main(["sysid", "excite", "--joints", ",".join(joints), *[x for kv in opts.items() for x in kv],
                 "--out", str(d / "plan.npz"), *m]) == 0
    assert main(["sysid", "simulate", str(d / "plan.npz"), "--patch", str(d / "truth.json"),
                 "--noise", "2e-4", "--seed", "3", "--out", str(d / "rec.npz"), *m]) == 0
    return m


@pytest.mark.parametrize("effect, joints, value", [
    ("kp_scale", ["shoulder", "elbow"], 0.6),          # a weak servo on two joints
    ("actuator_delay", ["elbow", "finger"], 0.03),     # a delay on two joints, one a 3 N·m/rad finger
])
def test_a_model_diagnosis_of_an_effect_on_two_joints_completes_and_its_patch_names_the_model(
        arm, tmp_path, capsys, effect, joints, value):
    # Effects selected on two joints are refitted jointly; that refit once built its patches without the
    # model, so a --model diagnosis crashed at the end ("this patch was fitted on model builtin", or an
    # unknown joint when the model's joint names are not adadex's).
    d, robot = tmp_path, ModelSource(arm).robot()
    m = _loop_files(arm, d, ModelPatch(robot=robot).with_effect(effect, joints, value), joints)
    assert main(["sysid", "diagnose", str(d / "rec.npz"), "--out", str(d / "D"), *m]) == 0
    diag = json.loads((d / "D" / "diagnosis.json").read_text())
    assert diag["model"] == robot.model_id and diag["verdict"] == "explained"
    [sel] = [s for s in diag["selected"] if s["effect"] == effect]
    assert sorted(sel["joints"]) == sorted(joints)
    pname = get_effect(effect).param_names[0]
    np.testing.assert_allclose(sel["params"][pname], value, rtol=0.1)

    assert main(["sysid", "fit", str(d / "rec.npz"), "--accept", str(d / "D"), "--out", str(d / "patch.json"), *m]) == 0
    assert json.loads((d / "patch.json").read_text())["model"] == robot.model_id
    capsys.readouterr()
    assert main(["sysid", "compare", str(d / "rec.npz"), "--patch", str(d / "patch.json"), *m]) == 0
    assert f"+ {effect} on " in capsys.readouterr().out
    rec = load_recording(d / "rec.npz", robot=robot)
    rep = Replayer(rec)
    before = np.sqrt(((rep.simulate() - rec.joint_pos) ** 2).mean())
    after = np.sqrt(((rep.simulate(ModelPatch.load(d / "patch.json", robot=robot)) - rec.joint_pos) ** 2).mean())
    assert after < 0.2 * before


def test_nothing_missing_on_a_user_model_names_the_model_and_accepting_it_adds_nothing(arm, tmp_path, capsys):
    d, robot = tmp_path, ModelSource(arm).robot()
    m = _loop_files(arm, d, ModelPatch(robot=robot), ["shoulder", "finger"], **{
        "--freqs": "1", "--amps": "0.5", "--kinds": "sine", "--poses": "home", "--duration": "1"})
    assert main(["sysid", "diagnose", str(d / "rec.npz"), "--out", str(d / "D"), *m]) == 0
    diag = json.loads((d / "D" / "diagnosis.json").read_text())
    assert diag["verdict"] == "nothing_missing"
    assert diag["model"] == robot.model_id           # was the stage times
    assert diag["train_only_joints"] == []           # was the model id
    assert set(diag["stage_times_s"]) >= {"localize"}
    assert all(isinstance(v, float) for v in diag["stage_times_s"].values())

    capsys.readouterr()
    assert main(["sysid", "fit", str(d / "rec.npz"), "--accept", str(d / "D"), "--out", str(d / "patch.json"), *m]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "nothing to add" in out[0]
    saved = json.loads((d / "patch.json").read_text())
    assert saved == {"version": 1, "model": robot.model_id, "effects": []}


def test_a_patch_takes_its_model_from_its_effects_and_refuses_to_mix_models(arm, tmp_path):
    robot = ModelSource(arm).robot()
    effect = ModelPatch(robot=robot).with_effect("damping", ["elbow"], 0.1).effects[0]
    patch = ModelPatch(effects=(effect,))             # no robot named: the effect's model, not the built-in one
    assert patch.model_id == robot.model_id and patch.effects[0].robot is robot
    other_arm = tmp_path / "other_arm.xml"
    other_arm.write_text(arm.read_text() + "<!-- another file, another model -->\n")
    other = ModelPatch(robot=ModelSource(other_arm).robot()).with_effect("damping", ["shoulder"], 0.1)
    with pytest.raises(PatchError, match="different models"):
        ModelPatch(effects=(effect, other.effects[0]))
    with pytest.raises(PatchError, match="fitted on model other_arm.xml"):
        patch.updated(other)


def test_every_patch_built_in_the_workbench_names_its_model_and_results_are_keyword_only():
    # A ModelPatch built without robot= is a patch of the built-in robot: inside adadex/sysid every one
    # names its model, and the result objects can only be built with keywords (a positional Diagnosis
    # once wrote the model id into train_only_joints).
    import ast
    from pathlib import Path

    import adadex.sysid

    unnamed, positional = [], []
    for path in sorted(Path(adadex.sysid.__file__).parent.glob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "ModelPatch"
                    and "robot" not in {k.arg for k in node.keywords}):
                unnamed.append(f"{path.name}:{node.lineno}")
            if isinstance(node, ast.ClassDef):
                for dec in node.decorator_list:
                    name = getattr(dec.func if isinstance(dec, ast.Call) else dec, "id", None)
                    kw = {k.arg: k.value for k in dec.keywords} if isinstance(dec, ast.Call) else {}
                    if name == "dataclass" and not (isinstance(kw.get("kw_only"), ast.Constant)
                                                    and kw["kw_only"].value is True):
                        positional.append(f"{path.name}:{node.name}")
    assert unnamed == [] and positional == []
