"""The workbench on data with hidden effects: the diagnosis never sees the truth patch."""

from typing import ClassVar

import pytest

from adadex.sim import effects as effects_mod
from adadex.sim.effects import Effect, Param, get_effect
from adadex.sim.patch import ModelPatch
from adadex.sysid.diagnose import diagnose
from adadex.sysid.excite import design_excitation, simulate_recording

NOISE = 2e-4


def _recording(joints, truth: ModelPatch, seed=0, poses=("loaded",)):
    """Sines at two frequencies and amplitudes and a chirp, 2 s each, per joint, in the loaded pose (and the
    unloaded one where a case needs it: ``BOTH_POSES``)."""
    plan = design_excitation(joints, freqs=(0.5, 2.0), amps=(0.3, 1.0), kinds=("sine", "chirp"), duration=2.0,
                             poses=poses)
    return simulate_recording(plan, truth, noise=NOISE, seed=seed)


def _top1_matches(d, effect, joint):
    """Top-ranked hypothesis for ``joint`` is ``effect``, or names it as an indistinguishable alternative."""
    top = next(h for h in d.hypotheses if h["joints"] == [joint])
    return top, top["effect"] == effect or effect in top["alternatives"]


CASES = [  # (effect, joint, value): one arm and one finger joint per library effect
    ("damping", "arm_j3", 8.0), ("damping", "if_pip", 0.08),
    ("coulomb_friction", "arm_j5", 1.5), ("coulomb_friction", "mf_pip", 0.05),
    ("armature", "arm_j5", 0.08), ("armature", "th_mcp", 0.006),
    ("actuator_delay", "arm_j2", 0.03), ("actuator_delay", "if_mcp", 0.04),
    ("actuator_lag", "arm_j4", 0.05), ("actuator_lag", "rf_pip", 0.06),
    ("torque_limit", "arm_j1", 0.3), ("torque_limit", "th_cmc", 0.4),
    ("kp_scale", "arm_j3", 0.6), ("kp_scale", "mf_mcp", 0.5),
    ("kd_scale", "arm_j6", 3.0), ("kd_scale", "if_dip", 3.0),
    ("payload_mass", "arm_j5", 1.0), ("payload_mass", "th_ipl", 0.1),
    ("joint_spring", "arm_j6", 60.0), ("joint_spring", "rf_mcp", 0.8),
    ("encoder_offset", "arm_j4", 0.02), ("encoder_offset", "if_rot", -0.03),
    ("backlash", "arm_j2", 0.01), ("backlash", "th_axl", 0.015),
]


#: cases the loaded pose alone does not show (2026-12-07): the thumb's last joint carries its payload
#: nearly along gravity there (nothing to see: "nothing missing"), and arm_j2's backlash (like arm_j5's
#: friction with armature, below) is explained to 80 % only with the unloaded pose's sequences beside it
BOTH_POSES = {("payload_mass", "th_ipl"), ("backlash", "arm_j2")}


@pytest.mark.parametrize("effect, joint, value", CASES, ids=[f"{e}-{j}" for e, j, _ in CASES])
def test_single_hidden_effect_is_found(effect, joint, value):
    truth = ModelPatch().with_effect(effect, [joint], value)
    poses = ("loaded", "unloaded") if (effect, joint) in BOTH_POSES else ("loaded",)
    d = diagnose(_recording([joint], truth, poses=poses), progress=False)
    assert d.verdict == "explained", d.findings
    top, ok = _top1_matches(d, effect, joint)
    assert ok, f"top-1 is {top['effect']} ({top['alternatives']}), truth {effect}"
    assert top["heldout_error_reduction"] >= 0.8
    if top["effect"] == effect:
        fitted = list(top["params"].values())[0][0]
        assert fitted == pytest.approx(value, rel=0.10), f"fitted {fitted}, truth {value}"


def test_two_effects_at_once_are_both_selected():
    truth = (ModelPatch().with_effect("coulomb_friction", ["if_pip"], 0.06)
             .with_effect("actuator_delay", ["arm_j2"], 0.025))
    d = diagnose(_recording(["if_pip", "arm_j2"], truth, seed=3), progress=False)
    assert d.verdict == "explained"
    sel = {(h["effect"], j): v for h in d.selected for j, v in zip(h["joints"], list(h["params"].values())[0])}
    assert set(sel) == {("coulomb_friction", "if_pip"), ("actuator_delay", "arm_j2")}
    assert sel[("coulomb_friction", "if_pip")] == pytest.approx(0.06, rel=0.1)
    assert sel[("actuator_delay", "arm_j2")] == pytest.approx(0.025, rel=0.1)


def test_two_effects_on_one_joint_forward_selection():
    truth = (ModelPatch().with_effect("coulomb_friction", ["arm_j5"], 1.5)
             .with_effect("armature", ["arm_j5"], 0.08))
    d = diagnose(_recording(["arm_j5"], truth, seed=4, poses=("loaded", "unloaded")), progress=False)
    chosen = {h["effect"] for h in d.selected}
    assert {"coulomb_friction", "armature"} <= chosen, d.findings
    assert d.verdict == "explained"


def test_lookalike_pair_is_one_hypothesis_with_alternatives():
    truth = ModelPatch().with_effect("damping", ["if_pip"], 0.08)
    d = diagnose(_recording(["if_pip"], truth, seed=5), progress=False)
    top, ok = _top1_matches(d, "damping", "if_pip")
    assert ok
    pair = {top["effect"], *top["alternatives"]}
    assert {"damping", "kd_scale"} <= pair


def test_null_case_nothing_missing():
    d = diagnose(_recording(["arm_j2", "if_pip"], ModelPatch(), seed=6), progress=False)
    assert d.verdict == "nothing_missing"
    assert d.selected == [] and d.hypotheses == []


class CubicDrag(Effect):
    """Test-only: drag growing with velocity cubed (MuJoCo dampingpoly), which the library lacks."""

    name, stage = "cubic_drag_test_only", "model"
    params: ClassVar = (Param("coef", "N·m·s²/rad²", 0.0, {g: 1.0 for g in effects_mod.GROUPS},
                              {g: 0.0 for g in effects_mod.GROUPS}, {g: 100.0 for g in effects_mod.GROUPS}),)

    def apply_model(self, m, base, jid, values):
        m.dof_dampingpoly[jid, 1] = values[:, 0]


def test_effect_outside_the_library_is_unexplained_or_clearly_partial(monkeypatch):
    monkeypatch.setitem(effects_mod.EFFECTS, CubicDrag.name, CubicDrag())
    truth = ModelPatch().with_effect(CubicDrag.name, ["if_pip"], 0.2)
    rec = _recording(["if_pip"], truth, seed=8)
    d = diagnose(rec, progress=False)
    assert CubicDrag.name not in {h["effect"] for h in d.hypotheses}
    best = max(h["heldout_error_reduction"] for h in d.hypotheses)
    assert d.verdict == "unexplained", (d.verdict, best)
    assert d.explained_fraction["if_pip"] < 0.8
    assert any("Unexplained" in f for f in d.findings)
    assert get_effect("damping")  # the library itself is untouched
