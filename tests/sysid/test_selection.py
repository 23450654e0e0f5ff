"""No spurious effect (issue 43): an effect is selected only if it explains a clear part of its joints'
held-out error beyond what the other selected effects explain; an effect at its absent value, or
explaining under 5 %, is never stored or printed as an explanation; a value on a bound is a suggestion
with the excitation that would identify it, not a selection.

The recording hides Coulomb friction on arm_j3 as a user would (MjSpec edit of the exported world,
2 s pre-roll at rest, noise; arm_j2 measured, holding its pose): the case where a damping on arm_j2 at
its bound and an actuator_lag on arm_j3 were once selected beside the friction."""

import numpy as np
import pytest

from adadex.sim.effects import get_effect
from adadex.sim.patch import ModelPatch
from adadex.sim.robot import GAINS
from adadex.sysid.compare import heldout_mask, noise_floor
from adadex.sysid.diagnose import MIN_EXPLAINED, Candidate, Diagnosis, _prune, _Setting, diagnose, on_bound
from adadex.sysid.replay import Replayer
from tests.sysid import hidden

FRICTION = 1.5
#: what the library's ``coulomb_friction`` (added to the model's own friction loss) should find: the edit
#: sets arm_j3's friction loss to FRICTION, the built-in shoulder's own is 0.2 N·m. (Before the windowed
#: friction fit, 2026-11-27, a local minimum of the free replay, 1.47, passed a check against FRICTION.)
ADDED = FRICTION - GAINS["arm_shoulder"].frictionloss


@pytest.fixture(scope="module")
def friction_recording():
    model = hidden.edited_model(hidden.frictionloss("arm_j3", FRICTION), "friction_arm_j3")
    return hidden.recording(model, ["arm_j3", "arm_j5"], measured=["arm_j2", "arm_j3", "arm_j5"],
                            poses=("loaded",), seed=1)


def _setting(rec) -> _Setting:
    rep = Replayer(rec)
    seq_meta = list(rec.meta["sequences"])
    return _Setting(replayer=rep, base_patch=ModelPatch(robot=rep.robot), joint_names=list(rec.joint_names),
                    noise=noise_floor(rec.joint_pos), seq_meta=seq_meta, holdout=heldout_mask(rec))


def _cand(effect, joint, value, ci95):
    return Candidate(effect=effect, joint=joint, value=value, ci95=ci95, train_error_reduction=0.5,
                     heldout_error_reduction=0.5, score=0.5)


def test_a_bound_an_absent_value_and_a_passenger_are_pruned_the_source_stays(friction_recording):
    setting = _setting(friction_recording)
    hi = float(get_effect("damping").bounds(["arm_j2"])[1][0, 0])
    friction = _cand("coulomb_friction", "arm_j3", FRICTION, (1.45, 1.55))
    selected = {"arm_j3": [friction, _cand("actuator_lag", "arm_j3", 0.004, (0.002, 0.006))],
                "arm_j2": [_cand("damping", "arm_j2", hi, (0.9 * hi, hi))],
                "arm_j5": [_cand("armature", "arm_j5", 0.0, (0.0, 1e-3))]}
    suggestions, removed = _prune(setting, selected, {}, {"arm_j3": ["arm_j2"]}, ["arm_j2", "arm_j3", "arm_j5"])
    assert selected == {"arm_j3": [friction], "arm_j2": [], "arm_j5": []}
    assert {(j, c.effect) for j, c in removed} == {("arm_j3", "actuator_lag"), ("arm_j2", "damping"),
                                                   ("arm_j5", "armature")}
    [s] = suggestions                       # only the value on a bound is suggested, with its excitation
    assert s["effect"] == "damping" and s["joints"] == ["arm_j2"]
    assert s["excite"].startswith("adadex sysid excite --joints arm_j2 --freqs")
    assert "Suggestion, not selected" in s["finding"] and s["excite"] in s["finding"]
    assert on_bound("damping", "arm_j2", hi, (0.9 * hi, hi)) and not on_bound("damping", "arm_j2", 1.0, (0.9, 1.1))
    assert not on_bound("damping", "arm_j2", 1e-3, (0.0, 0.01))      # reaching the absent value is not a bound


@pytest.fixture(scope="module")
def friction_diagnosis(friction_recording):
    return diagnose(friction_recording, progress=False)


def test_hidden_friction_is_the_only_explanation_and_nothing_below_five_percent_is_stored(friction_diagnosis, tmp_path):
    d = friction_diagnosis
    assert d.verdict == "explained", d.findings
    assert [(h["effect"], h["joints"]) for h in d.selected] == [("coulomb_friction", ["arm_j3"])], d.selected
    np.testing.assert_allclose(d.selected[0]["params"]["friction"], ADDED, rtol=0.1)
    assert d.suggestions == []
    for h in d.hypotheses:
        assert h["heldout_error_reduction"] >= MIN_EXPLAINED, h
        value = list(h["params"].values())[0][0]
        assert value != float(get_effect(h["effect"]).absent_values()[0]), h
    assert not any("explains 0%" in f for f in d.findings), d.findings
    d.save(tmp_path)
    assert Diagnosis.load(tmp_path).to_dict() == d.to_dict()


def test_an_effect_explaining_under_five_percent_of_a_joint_is_not_printed_as_its_explanation():
    from adadex.sysid.diagnose import _verdict

    load = _cand("payload_mass", "arm_j6", 0.6, (0.59, 0.61))
    verdict, findings = _verdict({"arm_j2": 0.9, "if_dip": 0.02}, {"arm_j2": [load], "if_dip": [load]}, 0.8)
    assert verdict == "unexplained"
    assert findings[0].startswith("arm_j2: payload_mass (mass = 0.6 kg) explains 90%")
    assert findings[1].startswith("if_dip: nothing explains 2%"), findings
