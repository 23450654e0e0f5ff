"""The user's loop through the ``adadex sysid`` command, and bad input."""

import json

import numpy as np
import pytest

from adadex.cli import main
from adadex.data.recording import Recording, load_recording
from adadex.sim.patch import ModelPatch
from adadex.sysid.replay import Replayer
from tests.sysid import demo_truth


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    d = tmp_path_factory.mktemp("loop")
    truth = ModelPatch().with_effect("backlash", ["if_dip"], 0.012)
    truth.save(d / "truth.json")
    assert main(["sysid", "excite", "--joints", "if_dip", "--freqs", "0.5,2", "--amps", "0.3,1",
                 "--kinds", "sine,chirp", "--duration", "2", "--out", str(d / "plan.npz")]) == 0
    assert main(["sysid", "simulate", str(d / "plan.npz"), "--patch", str(d / "truth.json"),
                 "--noise", "2e-4", "--seed", "1", "--out", str(d / "rec.npz")]) == 0
    return d


def test_simulated_recording_hides_the_truth(loop):
    rec = load_recording(loop / "rec.npz")
    assert rec.joint_names == ("if_dip",) and rec.num_sequences == 10
    assert "backlash" not in json.dumps(rec.meta)


def test_compare_diagnose_accept_and_watch_the_error_fall(loop, capsys):
    rec = loop / "rec.npz"
    assert main(["sysid", "compare", str(rec), "--out", str(loop / "cmp")]) == 0
    out = capsys.readouterr().out
    assert "fails on 1 of 1 joints: if_dip" in out
    summary = json.loads((loop / "cmp" / "compare.json").read_text())
    assert summary["localization"]["failing_joints"] == ["if_dip"]
    assert (loop / "cmp" / "heatmap.png").stat().st_size > 1000

    assert main(["sysid", "diagnose", str(rec), "--out", str(loop / "D")]) == 0
    diag = json.loads((loop / "D" / "diagnosis.json").read_text())
    assert diag["verdict"] == "explained"
    assert diag["hypotheses"][0]["effect"] == "backlash"
    assert {"effect", "joints", "params", "ci95", "train_error_reduction", "heldout_error_reduction",
            "alternatives"} <= set(diag["hypotheses"][0])
    assert diag["selected"][0]["params"]["half_width"][0] == pytest.approx(0.012, rel=0.1)

    assert main(["sysid", "fit", str(rec), "--accept", str(loop / "D"), "--out", str(loop / "patch.json")]) == 0
    patch = ModelPatch.load(loop / "patch.json")
    capsys.readouterr()
    assert main(["sysid", "compare", str(rec), "--patch", str(loop / "patch.json")]) == 0
    out = capsys.readouterr().out
    assert "+ backlash on if_dip" in out
    recording = load_recording(rec)
    rep = Replayer(recording)
    before = np.sqrt(((rep.simulate() - recording.joint_pos) ** 2).mean())
    after = np.sqrt(((rep.simulate(patch) - recording.joint_pos) ** 2).mean())
    assert after < 0.2 * before

    assert main(["sysid", "report", str(rec), "--patch", str(loop / "patch.json"), "--diagnosis",
                 str(loop / "D"), "--out", str(loop / "report.html")]) == 0
    html = (loop / "report.html").read_text()
    assert "The error falls" in html and "data:image/png;base64," in html
    assert "http://" not in html and "https://" not in html   # works offline


def test_fit_add_writes_a_patch_with_the_fitted_value(loop):
    assert main(["sysid", "fit", str(loop / "rec.npz"), "--add", "backlash:if_dip",
                 "--out", str(loop / "added.json")]) == 0
    p = json.loads((loop / "added.json").read_text())
    assert p["effects"][0]["effect"] == "backlash"
    assert p["effects"][0]["params"]["half_width"][0] == pytest.approx(0.012, rel=0.1)


@pytest.mark.parametrize("args, message", [
    (["fit", "REC", "--add", "coulomb_friction:arm_j1", "--out", "OUT"], "not in the recording"),
    (["fit", "REC", "--add", "stribeck:if_dip", "--out", "OUT"], "unknown effect"),
    (["fit", "REC", "--add", "backlash", "--out", "OUT"], "EFFECT:JOINT"),
    (["compare", "REC", "--patch", "MISSING.json"], "no such patch file"),
    (["diagnose", "MISSING.npz"], "No such file"),
    (["excite", "--joints", "if_dipp", "--out", "OUT"], "unknown joint"),
])
def test_user_errors_are_one_line_and_write_nothing(loop, tmp_path, capsys, args, message):
    args = [a.replace("REC", str(loop / "rec.npz")).replace("OUT", str(tmp_path / "out.json"))
            .replace("MISSING", str(tmp_path / "missing")) for a in args]
    assert main(["sysid", *args]) == 2
    assert message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_recording_with_nan_is_rejected_and_nothing_written(loop, tmp_path, capsys):
    rec = load_recording(loop / "rec.npz")
    arrays = rec.to_arrays()
    arrays["joint_pos"] = arrays["joint_pos"].copy()
    arrays["joint_pos"][3, 17, 0] = np.nan
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    assert main(["sysid", "diagnose", str(bad), "--out", str(tmp_path / "D")]) == 2
    err = capsys.readouterr().err
    assert "NaN" in err or "non-finite" in err
    assert not (tmp_path / "D").exists()


def test_shipped_demo_recording_is_reproducible():
    """assets/recordings/demo.npz is what tests/sysid/demo_truth.py makes (same seed, same bits)."""
    shipped = load_recording(demo_truth.DEMO)
    again = demo_truth.make_demo_recording()
    assert isinstance(shipped, Recording)
    np.testing.assert_array_equal(shipped.joint_pos, again.joint_pos)
    np.testing.assert_array_equal(shipped.command, again.command)


def test_nothing_missing_diagnosis_has_its_fields_and_accepting_it_adds_nothing(tmp_path, capsys):
    d = tmp_path
    assert main(["sysid", "excite", "--joints", "if_pip", "--freqs", "1", "--amps", "0.5", "--kinds", "sine",
                 "--poses", "unloaded", "--duration", "1", "--out", str(d / "plan.npz")]) == 0
    assert main(["sysid", "simulate", str(d / "plan.npz"), "--noise", "2e-4", "--out", str(d / "rec.npz")]) == 0
    assert main(["sysid", "diagnose", str(d / "rec.npz"), "--out", str(d / "D")]) == 0
    diag = json.loads((d / "D" / "diagnosis.json").read_text())
    assert diag["verdict"] == "nothing_missing" and diag["selected"] == []
    assert diag["model"] == "builtin" and diag["train_only_joints"] == []
    assert set(diag["stage_times_s"]) >= {"localize"}

    capsys.readouterr()
    assert main(["sysid", "fit", str(d / "rec.npz"), "--accept", str(d / "D"), "--out", str(d / "patch.json")]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "nothing to add" in out[0]
    assert json.loads((d / "patch.json").read_text()) == {"version": 1, "model": "builtin", "effects": []}
    # with a starting patch, the result is that patch unchanged
    base = ModelPatch().with_effect("damping", ["if_pip"], 0.05)
    base.save(d / "base.json")
    assert main(["sysid", "fit", str(d / "rec.npz"), "--accept", str(d / "D"), "--patch", str(d / "base.json"),
                 "--out", str(d / "patched.json")]) == 0
    assert ModelPatch.load(d / "patched.json").to_dict() == base.to_dict()
    assert "nothing to add" in capsys.readouterr().out

    # a nothing-missing diagnosis written by the earlier, positional Diagnosis reads as it was meant
    legacy = dict(diag, train_only_joints="builtin", model={"localize": 0.1}, stage_times_s={})
    (d / "old").mkdir()
    (d / "old" / "diagnosis.json").write_text(json.dumps(legacy))
    assert main(["sysid", "fit", str(d / "rec.npz"), "--accept", str(d / "old"), "--out", str(d / "p2.json")]) == 0
    assert "nothing to add" in capsys.readouterr().out
    # a diagnosis whose model is not a model id is refused in one line, not with a traceback
    (d / "bad").mkdir()
    (d / "bad" / "diagnosis.json").write_text(json.dumps(dict(diag, model=["builtin"])))
    assert main(["sysid", "fit", str(d / "rec.npz"), "--accept", str(d / "bad"), "--out", str(d / "p3.json")]) == 2
    assert "not a readable diagnosis" in capsys.readouterr().err


def test_an_excitation_with_an_unknown_kind_or_above_nyquist_is_refused():
    """Unknown waveforms were dropped silently (or failed inside numpy), and a multisine's top component
    (2.5 f) could pass the Nyquist frequency unnoticed."""
    from adadex.sysid.excite import ExcitationError, design_excitation

    with pytest.raises(ExcitationError, match=r"kinds: unknown excitation kind 'sweep'; choose from sine"):
        design_excitation(["if_pip"], kinds=("sine", "sweep"))
    with pytest.raises(ExcitationError, match="kinds: none given"):
        design_excitation(["if_pip"], kinds=())
    with pytest.raises(ExcitationError, match=r"multisine at 15 Hz reaches 37.5 Hz.*rate/2 = 30 Hz"):
        design_excitation(["if_pip"], freqs=(15.0,), rate=60.0)
    plan = design_excitation(["if_pip"], freqs=(15.0,), kinds=("sine",), rate=60.0)     # a sine at 15 Hz is fine
    assert len(plan.sequences) == 2 * 2                      # both poses × the two default amplitudes
