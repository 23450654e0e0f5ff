"""Channel L, the reference lead: no lead is the tracker itself, a lead of one control step on the
arm makes kinematic replay command the arm's reference one frame early (and leaves the hand's), the
lead chosen at an episode's first step holds for the episode, the view shows it, the policy graph
runs as the transformed env, and after the first step the ignored entries carry no log-probability."""

import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingConfig, TrackingEnv
from adadex.modules.channels import LEAD_STATE, ModulationConfig, ModulationLayout
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.transforms.modulation import modulation, read_ahead
from adadex.transforms.policy import make_policy
from tests.transforms.scripted import sampled_rollout, scripted_rollout

TARGET = ("next", "proprio", "joint_target")


def _plain(dataset, worlds=4, free=False):
    # free: targets move freely (the env clips a target's change per step to max_action, which would
    # make a lead catch up over the first steps)
    config = TrackingConfig(max_action=10.0) if free else TrackingConfig()
    return TrackingEnv(dataset, num_worlds=worlds, split=None, seed=3, randomize=Randomization.off(), config=config)


def _env(dataset, channels="L", config=ModulationConfig(), view=None, worlds=4, free=False):
    return TransformedEnv(_plain(dataset, worlds, free),
                          modulation(channels, Tracker.replay().freeze(), config=config, view=view))


def _rollout(dataset, script, steps=10, config=ModulationConfig(), free=False):
    return scripted_rollout(_env(dataset, config=config, free=free), script, 2, steps)


def test_read_ahead_is_exact_on_the_visible_frames_and_linear_between():
    frames = torch.randn(3, 5, 22)
    assert torch.equal(read_ahead(frames, torch.zeros(3, 22)), frames)
    one = read_ahead(frames, torch.ones(3, 22))
    torch.testing.assert_close(one[:, :2], frames[:, 1:3])                           # t → t+1, t+1 → t+2
    torch.testing.assert_close(one[:, 2], 0.5 * (frames[:, 2] + frames[:, 3]))       # t+3: between t+2 and t+4
    torch.testing.assert_close(one[:, 4], frames[:, 4])                              # held at t+12


def test_no_lead_is_replay_and_a_lead_of_one_step_commands_the_next_frame(tiny_dataset):
    assert ModulationLayout("L+C+T").channels == ("L", "C", "T") and ModulationLayout("L").dim == 2
    env = _plain(tiny_dataset, free=True)
    env.set_seed(3)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        replay = env.rollout(10, Tracker.replay().actor, break_when_any_done=False)
    env.close()
    assert torch.equal(_rollout(tiny_dataset, [[0.0, 0.0]], free=True)[TARGET], replay[TARGET])
    arm = _rollout(tiny_dataset, [[0.5, 0.0]], free=True)        # max_lead 2 → one step on the arm
    torch.testing.assert_close(arm[TARGET][:, :-1, :6], replay[TARGET][:, 1:, :6])
    assert torch.equal(arm[TARGET][..., 6:], replay[TARGET][..., 6:])
    hand = _rollout(tiny_dataset, [[0.0, 0.5]], free=True)       # one step on the hand
    torch.testing.assert_close(hand[TARGET][:, :-1, 6:], replay[TARGET][:, 1:, 6:])
    assert torch.equal(hand[TARGET][..., :6], replay[TARGET][..., :6])


def test_the_first_steps_lead_holds_for_the_episode_unless_unlatched(tiny_dataset):
    script = [[0.5, 0.25], [1.0, -1.0], [0.0, 1.0], [-1.0, 0.3], [0.9, 0.9]]
    latched = _rollout(tiny_dataset, script)
    constant = _rollout(tiny_dataset, [[0.5, 0.25]])
    assert torch.equal(latched[TARGET], constant[TARGET])
    torch.testing.assert_close(latched["next", LEAD_STATE], torch.tensor([1.0, 0.5, 1.0]).expand(4, 10, 3))
    free = _rollout(tiny_dataset, script, config=ModulationConfig(lead_latched=False))
    assert (free[TARGET] - constant[TARGET]).abs().max() > 1e-3
    assert LEAD_STATE not in free["next"].keys(True)


def test_a_reset_world_chooses_its_lead_again_and_the_view_shows_it(tiny_dataset):
    torch.manual_seed(0)
    mod = Modulator("L+T", hidden=(16, 16))
    env = _env(tiny_dataset, "L+T", view=mod.view, worlds=3)
    part = mod.view.slices()["lead"]
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        td = env.reset()
        assert td[LEAD_STATE].abs().max() == 0 and td["modulator", "view"][..., part].abs().max() == 0
        td = env.rollout(4, mod.actor, tensordict=td, auto_reset=False, break_when_any_done=False)
        first = 2.0 * td["action"][:, 0, :2].clamp(0, 1)
        torch.testing.assert_close(td["next", LEAD_STATE][..., :2], first[:, None].expand(3, 4, 2))
        torch.testing.assert_close(td["next", "modulator", "view"][..., part], td["next", LEAD_STATE][..., :2])
        nxt = td[:, -1]["next"].clone()
        nxt["_reset"] = torch.tensor([[True], [False], [False]])
        out = env.reset(nxt)
    assert out[LEAD_STATE][0].abs().max() == 0
    torch.testing.assert_close(out[LEAD_STATE][1:], td["next", LEAD_STATE][1:, -1])
    env.close()


def test_lead_in_the_policy_graph_runs_as_in_the_env_and_later_steps_carry_no_log_prob(tiny_dataset):
    torch.manual_seed(0)
    mod = Modulator("L+A+T", hidden=(16, 16))
    policy = make_policy(Tracker.replay().freeze(), mod)

    a = sampled_rollout(TransformedEnv(_plain(tiny_dataset, 2), policy.primer()), policy, 5)
    b = sampled_rollout(_env(tiny_dataset, "L+A+T", view=mod.view, worlds=2), mod.actor, 5)
    assert torch.equal(a["next", "proprio", "joint_pos"], b["next", "proprio", "joint_pos"])
    assert torch.equal(a["next", LEAD_STATE], b["next", LEAD_STATE])
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        td = _env(tiny_dataset, "L+A+T", view=mod.view, worlds=2).rollout(4, mod.sampling_policy(),
                                                                          break_when_any_done=False)
    loc, scale = td["modulator", "loc"][..., :3], td["modulator", "scale"][..., :3]    # L (2) and A (1)
    assert torch.equal(loc[:, 1:], torch.zeros(2, 3, 3)) and torch.equal(scale[:, 1:], torch.ones(2, 3, 3))
    assert (loc[:, 0] != 0).all()
