"""Domain randomization as a distribution over effect parameters: Table 3 by default, or ranges
around a patch fitted by the sysid workbench."""

import numpy as np
import pytest

from adadex.envs.randomization import EffectRange, Randomization
from adadex.envs.tracking import TrackingEnv
from adadex.sim.effects import EffectError
from adadex.sim.patch import ModelPatch, patched_scene

ROBOT_BODIES = ["link1", "link2", "link3", "link4", "link5", "link6", "palm", "if_bs", "if_px", "th_ds"]


def _world_models(dataset, randomize, seed, B=4):
    env = TrackingEnv(dataset, num_worlds=B, split=None, randomize=randomize, seed=seed, nthread=0)
    env.reset()
    models, patches = list(env.sim.models), list(env.world_patches)
    env.close()
    return models, patches


def test_table3_defaults_draw_robot_physics_per_world_within_range(tiny_dataset):
    models, patches = _world_models(tiny_dataset, Randomization(), seed=3)
    nom = patched_scene(None)
    bodies = [nom.body(n).id for n in ROBOT_BODIES]
    geoms = np.flatnonzero(np.isin(nom.geom_bodyid, bodies))
    ratios = []
    for m in models:
        assert [m.body(b).name for b in bodies] == ROBOT_BODIES
        kp = m.actuator_gainprm[:22, 0] / nom.actuator_gainprm[:22, 0]
        kv = m.actuator_biasprm[:22, 2] / nom.actuator_biasprm[:22, 2]
        damp = m.dof_damping[:22] / nom.dof_damping[:22]
        mass = m.body_mass[bodies] / nom.body_mass[bodies]
        fric = m.geom_friction[geoms, 0] / nom.geom_friction[geoms, 0]
        for r in (kp, kv, damp, mass, fric):        # one draw per world moves every joint alike (Table 3)
            assert np.allclose(r, r[0]) and 0.9 - 1e-12 <= r[0] <= 1.1 + 1e-12
        assert np.allclose(kv, damp)
        ratios.append([kp[0], damp[0], mass[0], fric[0]])
    ratios = np.array(ratios)
    assert all(len(np.unique(c)) == len(models) for c in ratios.T)      # every world its own draw
    assert sorted(e.effect for e in patches[0].effects) == ["damping_scale", "friction_scale", "kp_scale", "mass_scale"]
    again, _ = _world_models(tiny_dataset, Randomization(), seed=3)
    other, _ = _world_models(tiny_dataset, Randomization(), seed=4)
    assert all(np.array_equal(a.actuator_gainprm, b.actuator_gainprm) and np.array_equal(a.body_mass, b.body_mass)
               and np.array_equal(a.geom_friction, b.geom_friction) for a, b in zip(models, again))
    assert not np.array_equal(models[0].actuator_gainprm, other[0].actuator_gainprm)


def test_ranges_replace_table3_per_effect_and_joint_and_are_checked():
    r = Randomization(effects=(EffectRange("kp_scale", ("if_pip",), 0.5, 0.6),))
    kp = [x for x in r.effect_ranges() if x.effect == "kp_scale"]
    assert [x.joints for x in kp][-1] == ("if_pip",) and "if_pip" not in kp[0].joints and len(kp[0].joints) == 21
    assert Randomization.off().effect_ranges() == ()
    with pytest.raises(EffectError, match="only model-stage"):
        EffectRange("actuator_delay", ("arm_j1",), 0.0, 0.01)
    with pytest.raises(EffectError, match="outside"):
        Randomization(robot_mass=(0.1, 1.0))


def test_from_patch_without_intervals_falls_back_to_a_fraction():
    patch = ModelPatch().with_effect("kp_scale", ["if_pip"], 0.5).with_effect("backlash", ["if_dip"], 0.01)
    r = Randomization.from_patch(patch, fraction=0.2, base=Randomization.off())
    (kp,) = r.effect_ranges()
    assert kp.effect == "kp_scale" and np.allclose([kp.low[0, 0], kp.high[0, 0]], [0.4, 0.6])
    assert [e.effect for e in r.patch.effects] == ["kp_scale", "backlash"]     # backlash acts at its value


@pytest.fixture(scope="module")
def fitted_patch(tmp_path_factory):
    """Extra damping on if_pip hidden in a short simulated recording, fitted by ``adadex sysid fit``
    (the command a user runs), which writes the patch file with the fit's 95 % interval."""
    from adadex.cli import main
    from adadex.sysid.excite import design_excitation, simulate_recording

    d = tmp_path_factory.mktemp("fit")
    truth = ModelPatch().with_effect("damping", ["if_pip"], 0.08)
    plan = design_excitation(["if_pip"], freqs=(0.5, 2.0), amps=(0.3, 1.0), kinds=("sine",), duration=1.0)
    simulate_recording(plan, truth, noise=2e-4, seed=0).save(d / "rec.npz")
    assert main(["sysid", "fit", str(d / "rec.npz"), "--add", "damping:if_pip", "--out", str(d / "patch.json")]) == 0
    (fit,) = ModelPatch.load(d / "patch.json").effects
    value, (lo, hi) = float(fit.values[0, 0]), fit.ci95[0, 0]
    assert lo < value < hi and value == pytest.approx(0.08, rel=0.2)
    return d / "patch.json", (float(lo), float(hi))


def test_randomized_env_from_a_fitted_patch(tiny_dataset, fitted_patch):
    path, (lo, hi) = fitted_patch
    nominal = patched_scene(None).dof_damping[8]
    rnd = Randomization.from_patch(ModelPatch.load(path), base=Randomization.off())
    models, patches = _world_models(tiny_dataset, rnd, seed=1)
    extra = np.array([m.dof_damping[8] - nominal for m in models])
    assert ((extra >= lo - 1e-12) & (extra <= hi + 1e-12)).all(), (extra, lo, hi)
    assert len(np.unique(extra)) == len(models)                        # worlds differ
    assert np.allclose(extra, [p.effects[0].values[0, 0] for p in patches])
    again, _ = _world_models(tiny_dataset, rnd, seed=1)
    assert [m.dof_damping[8] for m in again] == [m.dof_damping[8] for m in models]

    # The one-liner, on top of Table 3: the fitted range replaces nothing else.
    env = TrackingEnv(tiny_dataset, num_worlds=2, split=None, randomize=Randomization.from_patch(ModelPatch.load(path)))
    env.reset()
    for p, m in zip(env.world_patches, env.sim.models):
        by = {e.effect: e for e in p.effects}
        assert set(by) == {"damping", "damping_scale", "friction_scale", "kp_scale", "mass_scale"}
        assert lo <= by["damping"].values[0, 0] <= hi
        s = by["damping_scale"].values[8, 0]
        assert m.dof_damping[8] == pytest.approx(s * nominal + by["damping"].values[0, 0])
    env.rollout(3)
    env.close()
