"""Effects that span joints: one effect on several joints is one hypothesis; absent values never count."""

import numpy as np
import pytest

from adadex.sim.patch import ModelPatch
from adadex.sysid.diagnose import diagnose
from adadex.sysid.excite import design_excitation, simulate_recording


@pytest.fixture(scope="module")
def delayed():
    joints = ["arm_j5", "if_pip", "mf_pip", "rf_pip"]
    truth = ModelPatch().with_effect("actuator_delay", joints, 0.05)
    plan = design_excitation(joints, freqs=(1.0, 3.0), amps=(0.5,), poses=("loaded",), kinds=("sine", "chirp"),
                             duration=2.0)
    rec = simulate_recording(plan, truth, noise=2e-4, seed=3)
    return joints, diagnose(rec, candidates=("actuator_delay", "actuator_lag", "kd_scale", "damping", "armature"),
                            progress=False), rec


def test_a_delay_on_the_arm_and_three_fingers_is_one_delay_hypothesis(delayed):
    joints, d, _ = delayed
    assert d.verdict == "explained"
    assert [h["effect"] for h in d.selected] == ["actuator_delay"]
    assert sorted(d.selected[0]["joints"]) == sorted(joints)
    np.testing.assert_allclose(d.selected[0]["params"]["delay"], 0.05, rtol=0.1)
    assert all(d.selected[0]["identifiable"])
    assert set(d.stage_times_s) >= {"localize", "fit", "relocalize"}


def test_explained_fractions_are_never_negative_and_absent_values_never_explain(delayed):
    _, d, _ = delayed
    assert all(v >= 0 for v in d.explained_fraction.values())
    assert all(h["heldout_error_reduction"] >= 0 for h in d.hypotheses)
    from adadex.sim.effects import get_effect

    for h in d.hypotheses:
        value = list(h["params"].values())[0][0]
        assert value != float(get_effect(h["effect"]).absent_values()[0]), h


def test_an_effect_on_several_joints_is_scored_per_joint_on_that_joints_own_held_out_sequences(delayed):
    from adadex.sysid.compare import heldout_mask, noise_floor
    from adadex.sysid.diagnose import _reduction
    from adadex.sysid.fit import JointFitter
    from adadex.sysid.replay import Replayer

    joints, d, rec = delayed
    rep, held = Replayer(rec), heldout_mask(rec)
    noise = noise_floor(rec.joint_pos)
    h = d.selected[0]
    for joint, reported in zip(h["joints"], h["heldout_error_reduction"]):
        own = [i for i, s in enumerate(rec.meta["sequences"]) if s["joint"] == joint and held[i]]
        f = JointFitter(rep, joint, own)
        expected = _reduction(f.mse_per_sequence(ModelPatch()), f.mse_per_sequence(d.patch()),
                              float(noise[list(rec.joint_names).index(joint)] ** 2))
        np.testing.assert_allclose(reported, expected, atol=1e-6, err_msg=joint)


def _diagnosed(truth, joints, candidates, *, freqs, poses, seed):
    """Diagnosis of a 2 s sine + chirp recording of ``joints`` made with ``truth`` hidden."""
    plan = design_excitation(joints, freqs=freqs, amps=(1.0,), poses=poses, kinds=("sine", "chirp"), duration=2.0)
    return diagnose(simulate_recording(plan, truth, noise=2e-4, seed=seed), candidates=candidates, progress=False)


@pytest.fixture(scope="module")
def shoulder_limited():
    # 0.45 of the effort still holds the arm up at rest; below ~0.36 the shoulder sags whenever another
    # joint moves, and the sag is so sensitive to the limit (0.3502 vs 0.35 leaves 15x-noise errors on the
    # fingers) that the fingers then fail as knock-ons: not covered yet.
    return _diagnosed(ModelPatch().with_effect("torque_limit", ["arm_j2"], 0.45),
                      ["arm_j2", "arm_j4", "if_pip", "mf_pip"],
                      ("torque_limit", "kp_scale", "armature", "damping"), freqs=(1.0, 3.0), poses=("loaded",), seed=4)


def test_a_saturating_shoulder_is_one_torque_limit_and_nothing_on_the_fingers(shoulder_limited):
    d = shoulder_limited
    assert d.verdict == "explained", d.findings
    assert [(h["effect"], h["joints"]) for h in d.selected] == [("torque_limit", ["arm_j2"])], d.selected
    np.testing.assert_allclose(d.selected[0]["params"]["fraction"], 0.45, rtol=0.05)


@pytest.fixture(scope="module")
def hand_payload():
    return _diagnosed(ModelPatch().with_effect("payload_mass", ["arm_j6"], 1.0),
                      ["arm_j2", "arm_j4", "arm_j6", "if_pip"],
                      ("payload_mass", "armature", "kp_scale", "damping"), freqs=(0.5, 3.0),
                      poses=("loaded", "unloaded"), seed=5)


def test_a_payload_on_the_hand_is_one_payload_on_one_link_not_split_over_the_arm(hand_payload):
    d = hand_payload
    assert d.verdict == "explained", d.findings
    assert [(h["effect"], h["joints"]) for h in d.selected] == [("payload_mass", ["arm_j6"])], d.selected
    np.testing.assert_allclose(d.selected[0]["params"]["mass"], 1.0, rtol=0.05)
    assert all(d.selected[0]["identifiable"])
    assert set(d.explained_fraction) == {"arm_j2", "arm_j4"}   # the joints that failed, all explained by the load
    assert min(d.explained_fraction.values()) >= 0.8
    assert any("one payload_mass on the link of arm_j6" in f for f in d.findings)
    assert d.hypotheses[0]["effect"] == "payload_mass" and d.hypotheses[0]["joints"] == ["arm_j6"]
