"""A model patch and domain randomization compose: each world's draw randomizes *around the patched
robot* — drawn scales multiply the patch's, drawn offsets add to them, within the effect's bounds —
and the ranges of ``Randomization.from_patch`` draw the fitted value itself (issue 42)."""

import dataclasses

import numpy as np
import pytest
import torch

from adadex.envs.randomization import EffectRange, Randomization
from adadex.envs.replay import replay_policy
from adadex.envs.tracking import TrackingEnv
from adadex.eval.metrics import from_rollout, summarize
from adadex.sim.effects import EFFECTS
from adadex.sim.patch import ModelPatch, patched_scene
from adadex.sim.robot import JOINT_NAMES, joint_index

ARM = [j for j in JOINT_NAMES if j.startswith("arm_")]
HAND = [j for j in JOINT_NAMES if not j.startswith("arm_")]
PIP = int(joint_index(["if_pip"])[0])          # its joint, dof and actuator index on the built-in robot
ON_OFF = {"off": Randomization.off(), "table3": Randomization()}


def _worlds(dataset, randomize, patch, seed=3, B=4):
    env = TrackingEnv(dataset, num_worlds=B, split=None, randomize=randomize, patch=patch, seed=seed, nthread=0)
    env.reset()
    models, patches = list(env.sim.models), list(env.world_patches)
    env.close()
    return models, patches


def _value(patch: ModelPatch, effect: str, joint: str) -> float:
    for e in patch.effects:
        if e.effect == effect and joint in e.joints:
            return float(e.values[e.joints.index(joint), 0])
    raise KeyError((effect, joint))


# ---------------------------------------------------------------- the declaration and the arithmetic

def test_every_effect_says_how_it_composes():
    scales = {"kp_scale", "kd_scale", "mass_scale", "friction_scale", "damping_scale", "torque_limit"}
    for name, eff in EFFECTS.items():
        assert eff.compositions == (("scale",) if name in scales else ("offset",)) * len(eff.params), name


def test_composed_multiplies_scales_adds_offsets_clips_and_keeps_the_rest():
    base = (ModelPatch().with_effect("kp_scale", ["arm_j1", "if_pip"], [0.3, 0.2])
            .with_effect("damping", ["if_pip"], 0.2).with_effect("encoder_offset", ["if_dip"], 0.08)
            .with_effect("actuator_delay", ["arm_j2"], 0.03))
    draw = (ModelPatch().with_effect("kp_scale", ["arm_j1", "if_pip", "if_dip"], [1.05, 0.9, 1.1])
            .with_effect("damping", ["if_pip", "if_dip"], [0.5, 0.1]).with_effect("encoder_offset", ["if_dip"], 0.05)
            .with_effect("actuator_delay", ["arm_j2"], 0.09))
    out = base.composed(draw)
    assert _value(out, "kp_scale", "arm_j1") == pytest.approx(0.315)            # 0.3 × 1.05
    assert _value(out, "kp_scale", "if_pip") == pytest.approx(0.2)              # 0.2 × 0.9 = 0.18, clipped to 0.2
    assert _value(out, "kp_scale", "if_dip") == pytest.approx(1.1)              # the draw alone
    assert _value(out, "damping", "if_pip") == pytest.approx(0.6)               # 0.2 + 0.5, clipped to 0.6
    assert _value(out, "damping", "if_dip") == pytest.approx(0.1)
    assert _value(out, "encoder_offset", "if_dip") == pytest.approx(0.1)        # 0.08 + 0.05, clipped to 0.1
    assert _value(out, "actuator_delay", "arm_j2") == pytest.approx(0.1)        # 0.03 + 0.09, clipped to 0.1
    assert out.composed(ModelPatch()) == out and ModelPatch().composed(draw) == draw
    # updated keeps its replace semantics (the sysid fit relies on them)
    assert _value(base.updated(draw), "kp_scale", "arm_j1") == pytest.approx(1.05)
    # the compiled model holds the composition
    m = out.build_model()
    nom = patched_scene(None)
    assert m.actuator_gainprm[0, 0] == pytest.approx(nom.actuator_gainprm[0, 0] * 0.315)
    assert m.dof_damping[PIP] == pytest.approx(nom.dof_damping[PIP] + 0.6)


# ---------------------------------------------------------------- each effect kind × randomization on/off

@pytest.mark.parametrize("rnd", ON_OFF, ids=list(ON_OFF))
def test_a_scale_patch_is_randomized_around_not_dropped(tiny_dataset, rnd):
    """kp_scale 0.3 on the arm, 0.2 on six finger joints: arm_j1's gain is 1500 · 0.3 · draw (not
    1500 · draw), the fingers' 0.2 · draw clipped to kp_scale's lower bound 0.2."""
    fingers = HAND[:6]
    patch = ModelPatch().with_effect("kp_scale", ARM, 0.3).with_effect("kp_scale", fingers, 0.2)
    models, patches = _worlds(tiny_dataset, ON_OFF[rnd], patch)
    nom = patched_scene(None)
    gain = lambda m, j: m.actuator_gainprm[j, 0] / nom.actuator_gainprm[j, 0]      # noqa: E731
    free = JOINT_NAMES.index(HAND[-1])                      # a joint the patch leaves alone: the draw itself
    draws = []
    for m, p in zip(models, patches):
        draw = gain(m, free)
        assert (draw == 1.0) if rnd == "off" else (0.9 - 1e-9 <= draw <= 1.1 + 1e-9)
        assert nom.actuator_gainprm[0, 0] == 1500.0
        assert m.actuator_gainprm[0, 0] == pytest.approx(1500.0 * 0.3 * draw)
        assert m.actuator_biasprm[0, 1] == pytest.approx(-1500.0 * 0.3 * draw)
        for j in ARM:
            assert gain(m, JOINT_NAMES.index(j)) == pytest.approx(0.3 * draw)
            assert _value(p, "kp_scale", j) == pytest.approx(0.3 * draw)
        for j in fingers:
            assert gain(m, JOINT_NAMES.index(j)) == pytest.approx(max(0.2 * draw, 0.2))
        draws.append(draw)
    if rnd == "table3":
        assert len(set(draws)) == len(models)              # still one draw per world


@pytest.mark.parametrize("rnd", ON_OFF, ids=list(ON_OFF))
def test_an_offset_patch_adds_to_the_drawn_offset(tiny_dataset, rnd):
    """damping 0.2 and armature 0.01 on if_pip under ranges of the same effects: the model holds
    nominal (× Table 3's damping scale) + 0.2 + the drawn extra, not the drawn extra alone."""
    ranges = (EffectRange("damping", ("if_pip",), 0.0, 0.1), EffectRange("armature", ("if_pip",), 0.0, 0.005))
    randomize = ON_OFF[rnd] if rnd == "off" else dataclasses.replace(ON_OFF[rnd], effects=ranges)
    patch = ModelPatch().with_effect("damping", ["if_pip"], 0.2).with_effect("armature", ["if_pip"], 0.01)
    models, patches = _worlds(tiny_dataset, randomize, patch)
    nom = patched_scene(None)
    extras = []
    for m, p in zip(models, patches):
        s = _value(p, "damping_scale", "if_pip") if rnd == "table3" else 1.0
        damping, armature = _value(p, "damping", "if_pip"), _value(p, "armature", "if_pip")
        if rnd == "off":
            assert (damping, armature) == (0.2, 0.01)
        else:
            assert 0.2 <= damping <= 0.3 and 0.01 <= armature <= 0.015
        assert m.dof_damping[PIP] == pytest.approx(s * nom.dof_damping[PIP] + damping)
        assert m.dof_armature[PIP] == pytest.approx(nom.dof_armature[PIP] + armature)
        extras.append(damping)
    if rnd == "table3":
        assert len(set(extras)) == len(models)


@pytest.mark.parametrize("rnd", ON_OFF, ids=list(ON_OFF))
def test_structure_and_sensor_effects_act_at_the_patch_value_in_every_world(tiny_dataset, rnd):
    """Delays and encoder offsets are not drawn per world: the patch's value acts in every world,
    randomized or not (regression guard: this held before the fix too)."""
    randomize = dataclasses.replace(ON_OFF[rnd], proprio_noise=0.0)
    patch = ModelPatch().with_effect("actuator_delay", ["arm_j1"], 0.03).with_effect("encoder_offset", ["if_pip"], 0.05)
    seen = {}
    for name, p in (("patched", patch), ("plain", None)):
        env = TrackingEnv(tiny_dataset, num_worlds=3, split=None, randomize=randomize, patch=p, seed=5, nthread=0)
        td = env.reset()
        seen[name] = td["proprio", "joint_pos"].numpy().astype(np.float64)
        if name == "patched":
            for m, wp in zip(env.sim.models, env.world_patches):
                assert m.actuator_delay[0] == pytest.approx(0.03)
                assert _value(wp, "actuator_delay", "arm_j1") == 0.03
                assert _value(wp, "encoder_offset", "if_pip") == 0.05
        env.close()
    diff = seen["patched"] - seen["plain"]
    assert np.allclose(diff[:, PIP], 0.05, atol=1e-5)
    assert np.allclose(np.delete(diff, PIP, axis=1), 0.0, atol=1e-5)


# ---------------------------------------------------------------- from_patch: the draws are the values

def test_from_patch_draws_the_fitted_value_within_its_interval_and_composes_with_the_rest(tiny_dataset):
    """A fit of kp_scale on arm_j1 (0.5, 95 % interval [0.45, 0.55]) given both as the env's patch and
    as from_patch's source: arm_j1's gain is 1500 · a draw in [0.45, 0.55] (the fit is not applied a
    second time on top), while the env patch's kp_scale 0.3 on arm_j2 still composes with Table 3."""
    fit = ModelPatch.from_dict({"effects": [{"effect": "kp_scale", "joints": ["arm_j1"], "params": {"scale": [0.5]},
                                             "ci95": {"scale": [[0.45, 0.55]]}}]})
    rnd = Randomization.from_patch(fit)
    (kp,) = [r for r in rnd.effects if r.effect == "kp_scale"]
    assert kp.absolute and (kp.low[0, 0], kp.high[0, 0]) == pytest.approx((0.45, 0.55))
    patch = fit.updated(ModelPatch().with_effect("kp_scale", ["arm_j2"], 0.3))
    models, patches = _worlds(tiny_dataset, rnd, patch, B=6)
    nom = patched_scene(None)
    j1 = []
    for m, p in zip(models, patches):
        draw = m.actuator_gainprm[2, 0] / nom.actuator_gainprm[2, 0]       # arm_j3: Table 3 alone
        assert 0.45 - 1e-9 <= m.actuator_gainprm[0, 0] / 1500.0 <= 0.55 + 1e-9
        assert _value(p, "kp_scale", "arm_j1") == pytest.approx(m.actuator_gainprm[0, 0] / 1500.0)
        assert m.actuator_gainprm[1, 0] == pytest.approx(nom.actuator_gainprm[1, 0] * 0.3 * draw)
        j1.append(m.actuator_gainprm[0, 0])
    assert len(set(j1)) == len(models)


# ---------------------------------------------------------------- the replay figure

def _replay(dataset, randomize, patch):
    env = TrackingEnv(dataset, num_worlds=6, split=None, randomize=randomize, patch=patch, seed=0, nthread=0,
                      draw="cycle")
    torch.manual_seed(0)
    td = env.rollout(env.config.window - 1, replay_policy(), break_when_any_done=False)
    env.close()
    return summarize(from_rollout(td))


def test_replay_with_a_kp_patch_differs_under_randomization(tiny_dataset):
    """Kinematic replay on the tiny dataset under Table 3: the arm's kp × 0.3 shows (the palm lags
    its reference about 3× as far, as it does without randomization) instead of vanishing."""
    patch = ModelPatch().with_effect("kp_scale", ARM, 0.3)
    nominal = _replay(tiny_dataset, Randomization(), None)
    patched = _replay(tiny_dataset, Randomization(), patch)
    unrandomized = _replay(tiny_dataset, Randomization.off(), patch)
    assert patched["T_h"] > 2 * nominal["T_h"], (patched, nominal)
    assert patched["completion_pct"] != nominal["completion_pct"]
    assert patched["T_h"] == pytest.approx(unrandomized["T_h"], rel=0.25)


@pytest.mark.parametrize("effect, params", [("actuator_delay", {"delay": 0.08}), ("actuator_lag", {"tau": 0.1})])
def test_a_delayed_or_lagged_robot_starts_an_episode_holding_its_pose(tiny_dataset, effect, params):
    """The episode's first targets are the pose the robot holds at reset: a delayed or lagged servo
    has been receiving them (its history and activation hold them), so replay's first step moves the
    joints by the reference's own step, not towards 0 rad (the jolt that knocked objects over)."""
    patch = ModelPatch.from_dict({"version": 1, "model": "builtin", "effects": [
        {"effect": effect, "joints": ARM, "params": params}]})
    out = {}
    for name, p in (("nominal", None), ("patched", patch)):
        env = TrackingEnv(tiny_dataset, num_worlds=4, split=None, randomize=Randomization.off(), patch=p, seed=3,
                          nthread=0)
        td = env.reset()
        with torch.no_grad():
            td = env.step(replay_policy()(td))
        out[name] = (td["next", "proprio", "joint_pos"] - td["proprio", "joint_pos"]).abs()[:, :6].max()
        env.close()
    assert out["patched"] < out["nominal"] + 0.02, out
