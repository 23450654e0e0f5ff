"""TrackingEnv: specs, resets, stepping, unstable worlds, replay — on a tiny dataset built once."""

import copy
import dataclasses

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from adadex.envs.replay import replay_policy
from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingConfig, TrackingEnv


@pytest.fixture(scope="module")
def dataset(tiny_dataset):
    return tiny_dataset


@pytest.fixture
def env(dataset):
    e = TrackingEnv(dataset, num_worlds=4, split=None, seed=0)
    yield e
    e.close()


@pytest.mark.parametrize("B", [1, 8])
def test_check_env_specs(dataset, B):
    env = TrackingEnv(dataset, num_worlds=B, split=None)
    check_env_specs(env)
    env.close()


def test_reset_starts_on_the_reference(env):
    td = env.reset()
    assert td["observation"].shape == (4, 273)
    assert (td["privileged", "errors", "T_h"] < 1e-5).all() and (td["privileged", "errors", "E_finger"] < 1e-6).all()
    assert (td["privileged", "errors", "T_o"] <= env.config.object_lift + 1e-5).all()
    assert not td["privileged", "unstable"].any()


def test_worlds_may_hold_different_objects(dataset):
    env = TrackingEnv(dataset, num_worlds=8, split=None, seed=1)
    env.reset()
    objects = {env.dataset.entries[int(i)]["object"] for i in env._ref_index}
    assert len(objects) > 1
    td = env.rollout(6, replay_policy(), break_when_any_done=False)
    # The hand starts far away: every object stays where its reference puts it.
    assert (td["next", "privileged", "errors", "T_o"] < 0.01).all(), td["next", "privileged", "errors", "T_o"]
    env.close()


def test_replay_tracks_the_hand_reference(env):
    td = env.rollout(40, replay_policy(), break_when_any_done=False)
    th = td["next", "privileged", "errors", "T_h"]
    assert th.shape == (4, 40) and th.max() < 0.05, th.max()
    assert td["next", "privileged", "errors", "E_finger"].mean() < 0.05
    assert torch.isfinite(td["next", "reward"]).all()


def test_partial_reset_touches_only_flagged_worlds(env):
    env.reset()
    td = env.rand_step(env.reset())
    before = env._t.copy()
    refs = env._ref_index.copy()
    mask = torch.zeros(4, 1, dtype=torch.bool)
    mask[2] = True
    out = env.reset(td["next"].clone().set("_reset", mask))
    assert env._t.tolist() == [int(before[0]), int(before[1]), 0, int(before[3])]
    assert np.array_equal(np.delete(env._ref_index, 2), np.delete(refs, 2))
    assert torch.equal(out["observation"][[0, 1, 3]], td["next", "observation"][[0, 1, 3]])


def test_truncation_at_the_window_end(dataset):
    env = TrackingEnv(dataset, num_worlds=2, split=None, config=TrackingConfig(window=20))
    td = env.rollout(25, replay_policy(), break_when_any_done=False)
    trunc = td["next", "truncated"][..., 0]
    assert trunc[:, 18].all() and not trunc[:, :18].any()
    env.close()


def test_unstable_world_is_reset_alone_and_counted(env):
    td = env.reset()
    good = env.sim.models[1]
    bad = copy.copy(good)
    assert bad is not good
    bad.opt.gravity[:] = (0.0, 0.0, -1e12)      # MuJoCo flags the huge accelerations and resets the world
    env.sim.set_models([1], [bad])
    td = env.rand_step(td)
    nxt = td["next"]
    assert nxt["privileged", "unstable"][:, 0].tolist() == [False, True, False, False]
    assert nxt["terminated"][:, 0].tolist()[1] is True and not nxt["terminated"][[0, 2, 3]].any()
    assert torch.isfinite(nxt["observation"]).all()
    assert env.unstable_count == 1


def test_same_seed_same_rollout(dataset):
    outs = []
    for _ in range(2):
        env = TrackingEnv(dataset, num_worlds=3, split=None, seed=7)
        outs.append(env.rollout(5, replay_policy(), break_when_any_done=False))
        env.close()
    assert torch.equal(outs[0]["next", "observation"], outs[1]["next", "observation"])


def test_a_world_that_ends_early_leaves_the_others_noise_alone(dataset):
    """Two rollouts with one seed, under Table 3's noise, differing only in world 0, which the
    second drives away until it terminates and restarts: the other worlds see the same noisy
    observations at every step (per-step noise has its own stream; a restart draws from the other)."""
    def away(td):
        td = replay_policy()(td)
        td["action"][0] = torch.where(torch.arange(22) < 6, 0.5, 0.0)       # the arm's joints, all one way
        return td

    outs = []
    for policy in (replay_policy(), away):
        env = TrackingEnv(dataset, num_worlds=3, split=None, seed=11, randomize=Randomization())
        outs.append(env.rollout(40, policy, break_when_any_done=False))
        env.close()
    replay, pushed = outs
    assert pushed["next", "terminated"][0].any() and not replay["next", "terminated"][0].any()
    assert torch.equal(replay["next", "observation"][1:], pushed["next", "observation"][1:])
    assert not torch.equal(replay["next", "observation"][0], pushed["next", "observation"][0])


def test_step_output_is_complete_without_torchrl_completion(dataset):
    """The env skips TorchRL's reshape-and-fill pass over each step's output: with ``run_type_checks``
    (which runs that pass and TorchRL's type checks) the rollout is the same, key for key."""
    outs = []
    for checks in (False, True):
        env = TrackingEnv(dataset, num_worlds=3, split=None, seed=7)
        env.run_type_checks = checks
        outs.append(env.rollout(5, replay_policy(), break_when_any_done=False))
        env.close()
    fast, checked = outs
    assert set(fast.keys(True, True)) == set(checked.keys(True, True))
    assert (fast == checked).all()
    assert fast["next", "reward"].shape == (3, 5, 1) and fast["next", "done"].dtype == torch.bool


def test_bad_config(dataset):
    with pytest.raises(ValueError, match="window"):
        TrackingConfig(window=5)
    with pytest.raises(ValueError, match="max_action"):
        TrackingConfig(max_action=-1)
    with pytest.raises(ValueError, match="num_worlds"):
        TrackingEnv(dataset, num_worlds=0)


# ------------------------------------------------------------------------------------------------
# Randomization and effects


@pytest.mark.parametrize("B", [1, 8])
def test_check_env_specs_with_randomization(dataset, B):
    env = TrackingEnv(dataset, num_worlds=B, split=None, randomize=Randomization())
    check_env_specs(env)
    env.close()


def test_randomization_varies_physics_per_world_and_is_seeded(dataset):
    def draw(seed):
        env = TrackingEnv(dataset, num_worlds=6, split=None, randomize=Randomization(), seed=seed)
        td = env.reset()
        kp = np.array([m.actuator_gainprm[0, 0] for m in env.sim.models])
        mass = np.array([m.body("object").mass[0] for m in env.sim.models])
        env.close()
        return kp, mass, td["object", "pose"]

    kp, mass, pose = draw(3)
    assert len(np.unique(kp)) == 6 and len(np.unique(mass)) == 6
    nominal = TrackingEnv(dataset, num_worlds=1, split=None).sim.models[0].actuator_gainprm[0, 0]
    assert (np.abs(kp / nominal - 1) <= 0.1 + 1e-9).all()
    kp2, mass2, pose2 = draw(3)
    assert np.array_equal(kp, kp2) and np.array_equal(mass, mass2) and torch.equal(pose, pose2)
    assert not np.array_equal(kp, draw(4)[0])


def test_randomization_off_equals_none(dataset):
    outs = []
    for rnd in (None, Randomization.off()):
        env = TrackingEnv(dataset, num_worlds=2, split=None, randomize=rnd, seed=5)
        outs.append(env.rollout(4, replay_policy(), break_when_any_done=False))
        env.close()
    assert torch.allclose(outs[0]["next", "observation"], outs[1]["next", "observation"], atol=1e-6)


def test_effects_and_patches_reach_every_world(dataset, tmp_path):
    from adadex.sim.patch import ModelPatch

    env = TrackingEnv(dataset, num_worlds=3, split=None, effects=[("damping", ["arm_j2"], [[0.5]])])
    env.reset()
    plain = TrackingEnv(dataset, num_worlds=1, split=None)
    j2 = 1
    assert all(m.dof_damping[j2] > plain.sim.models[0].dof_damping[j2] + 0.4 for m in env.sim.models)
    path = ModelPatch().with_effect("encoder_offset", ["if_pip"], [[0.05]]).save(tmp_path / "p.json")
    env2 = TrackingEnv(dataset, num_worlds=2, split=None, patch=path)
    td = env2.reset()
    # The encoder reports 0.05 rad more than the joint: seen in the observation, not in the errors.
    assert torch.allclose(td["proprio", "joint_pos"][:, 8] - torch.from_numpy(env2.sim.readout().joint_pos[:, 8]).float(), torch.tensor(0.05))
    for e in (env, plain, env2):
        e.close()


def test_backlash_runs_online(dataset):
    """A command-stage effect: the servo target trails the commanded target by the play b."""
    b = 0.03
    env = TrackingEnv(dataset, num_worlds=1, split=None, effects=[("backlash", ["if_pip"], [[b]])])
    td = env.reset()
    start = float(env._servo_cmd[0, 8])
    for k in range(1, 4):                     # command if_pip up by 0.02 rad per step
        act = torch.zeros(1, 22)
        act[0, 8] = 0.02
        td = env.step(td.set("action", act))["next"]
        target = float(env._q_target[0, 8])
        assert target == pytest.approx(start + 0.02 * k)
        assert float(env._servo_cmd[0, 8]) == pytest.approx(max(start, target - b))
    env.close()


def test_gymnasium_registration_and_env_checker(dataset):
    import gymnasium
    from gymnasium.utils.env_checker import check_env

    import adadex.envs  # noqa: F401  (registers the id)

    env = gymnasium.make("adadex/Tracking-v0", dataset=str(dataset), split=None)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert obs.shape == (273,) and set(info) >= {"T_o", "R_o", "T_h", "R_h", "E_finger", "reference"}
    obs2, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert np.isfinite(obs2).all() and np.isfinite(reward) and not truncated
    env.close()


def test_cycle_draws_every_reference_once(dataset):
    env = TrackingEnv(dataset, num_worlds=2, split=None, draw="cycle")
    env.reset()
    first = list(env._ref_index)
    env.reset()
    second = list(env._ref_index)
    n = len(env.references)
    assert first == env.references[:2] and second == [env.references[2 % n], env.references[3 % n]]
    with pytest.raises(ValueError, match="draw"):
        TrackingEnv(dataset, num_worlds=1, draw="sometimes")
    env.close()


def test_flung_object_counts_as_unstable(dataset):
    """Object speed above max_object_speed is a solver blow-up: flagged, put back, counted."""
    env = TrackingEnv(dataset, num_worlds=3, split=None, config=TrackingConfig(max_object_speed=1e-9))
    td = env.rand_step(env.reset())["next"]     # the objects settle the 2 mm they start above the table
    assert td["privileged", "unstable"].all() and td["terminated"].all() and env.unstable_count == 3
    assert (td["privileged", "errors", "T_o"] <= env.config.object_lift + 1e-5).all()   # back at the start pose
    env.close()


def test_action_noise_is_in_units_of_the_action_bound_and_clipped_to_it(dataset):
    """Table 3's action noise is IsaacGymEnvs' (added to the normalized action before the clip)."""
    rnd = dataclasses.replace(Randomization.off(), action_noise_uncorrelated=0.5)
    env = TrackingEnv(dataset, num_worlds=8, split=None, seed=0, randomize=rnd, config=TrackingConfig(max_action=0.04))
    td = env.reset()
    steps = []
    for _ in range(6):
        td = env.step(td.set("action", torch.zeros(8, 22)))
        steps.append(td["next", "proprio", "joint_target"] - td["proprio", "joint_target"])
        td = td["next"]
    change = torch.stack(steps)
    assert change.abs().max() <= 0.04 + 1e-6                          # never past the bound
    # N(0, 0.5 · 0.04) clipped at ±0.04 has a std of 0.0186 (read in rad it would be nearly all ±0.04)
    assert 0.015 < change.std() < 0.021, change.std()
    env.close()
