"""A modulator that decides every k steps (``Modulator(decide_every=k)``): the env holds its action for
the k steps, the view says where it holds, the heads are a fixed N(0, 1) there (no parameter's
log-probability), the policy graph runs as the transformed env, and a latched channel stays latched."""

import csv

import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from adadex.errors import ConfigError
from adadex.envs.tracking import TrackingEnv
from adadex.eval.figures import channel_usage
from adadex.modules.channels import REACH_STATE
from adadex.modules.modulator import Modulator
from adadex.modules.modulator_view import LAST_ACTION, ViewLayout
from adadex.modules.tracker import Tracker
from adadex.transforms.modulation import modulation
from adadex.transforms.policy import make_policy
from tests.transforms.scripted import sampled_rollout

K = 3


def _env(dataset, mod, worlds=3):
    return TransformedEnv(TrackingEnv(dataset, num_worlds=worlds, split=None, seed=3),
                          modulation(mod.layout.channels, Tracker.replay().freeze(), view=mod.view))


def _sampled(dataset, mod, steps=7):
    env = _env(dataset, mod)
    check_env_specs(env)
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        td = env.rollout(steps, mod.actor, break_when_any_done=False)
    env.close()
    return td


def test_the_action_holds_between_decisions_and_the_view_says_where(tiny_dataset):
    torch.manual_seed(0)
    mod = Modulator("R+T", hidden=(16, 16), decide_every=K)
    assert [n for n, _ in mod.view.parts][-2:] == ["held", "history"]
    assert ViewLayout("R+T").dim + 1 == mod.view.dim and mod.config["decide_every"] == K
    td = _sampled(tiny_dataset, mod)
    applied = td["next", *LAST_ACTION]                      # what the env applied at each step
    held = td["modulator", "view"][..., mod.view.slices()["held"]][..., 0]
    assert torch.equal(held[0], torch.tensor([0., 1., 1., 0., 1., 1., 0.]))
    for t in range(7):
        decision = t - t % K
        torch.testing.assert_close(applied[:, t], td["action"][:, decision].clamp(-1, 1))
    assert (td["action"][:, 1] - td["action"][:, 0]).abs().max() > 0.01        # the samples did differ
    # the reference edit R carries grows by the held residual at every step, decided or not
    assert (td["next", "modulation", "hand_edit"][:, 2] - td["next", "modulation", "hand_edit"][:, 1]).abs().max() > 0


def test_between_decisions_no_entry_carries_a_parameters_log_probability(tiny_dataset):
    torch.manual_seed(0)
    mod = Modulator("T", hidden=(16, 16), decide_every=K)
    td = _sampled(tiny_dataset, mod, steps=6)
    loc, scale = td["modulator", "loc"], td["modulator", "scale"]
    between = td[:, [1, 2, 4, 5]].reshape(-1).clone()
    assert torch.equal(between["modulator", "loc"], torch.zeros_like(between["modulator", "loc"]))
    assert torch.equal(between["modulator", "scale"], torch.ones_like(between["modulator", "scale"]))
    assert (scale[:, 0] - 1).abs().max() > 0.1 and (scale[:, 3] - 1).abs().max() > 0.1   # T's own scale where it decides
    mod.actor.get_dist(between).log_prob(between["action"]).sum().backward()
    assert all(p.grad is None or p.grad.abs().max() == 0 for p in mod.actor.parameters())
    decided = td[:, [0, 3]].reshape(-1).clone()
    mod.actor.get_dist(decided).log_prob(decided["action"]).sum().backward()
    assert mod.heads.heads[0].weight.grad.abs().max() > 0
    assert loc.shape[-1] == 22


def test_the_policy_graph_holds_as_the_env_does(tiny_dataset):
    mod = Modulator("R+T", hidden=(16, 16), decide_every=K)
    policy = make_policy(Tracker.replay().freeze(), mod)
    a = sampled_rollout(TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3), policy.primer()),
                        policy, 6)
    b = sampled_rollout(_env(tiny_dataset, mod, worlds=2), mod.actor, 6)
    assert torch.equal(a["next", "proprio", "joint_pos"], b["next", "proprio", "joint_pos"])
    # the channels' usage is that of the held actions the env applied, not of the ignored samples
    decided = a["modulation", "sample"][:, [0, 0, 0, 3, 3, 3], 112:]
    assert channel_usage([a], "R+T")["action"] == pytest.approx(float(decided.abs().mean()), rel=1e-5)


def test_a_latched_channel_stays_latched_at_later_decisions(tiny_dataset):
    torch.manual_seed(0)
    mod = Modulator("A+T", hidden=(16, 16), decide_every=2)
    td = _sampled(tiny_dataset, mod, steps=5)
    reach = td["next", REACH_STATE][..., 0]
    assert torch.equal(reach, reach[:, :1].expand_as(reach))       # chosen at the first step, kept
    at_two = td[:, 2]                                               # a decision: T live, A fixed
    assert torch.equal(at_two["modulator", "loc"][..., 0], torch.zeros(3))
    assert (at_two["modulator", "scale"][..., 1:] - 1).abs().max() > 0.1


def test_a_saved_modulator_keeps_its_decision_interval(tmp_path):
    mod = Modulator("T", hidden=(16, 16), decide_every=4)
    mod.save(tmp_path / "m.pt")
    assert Modulator.load(tmp_path / "m.pt").view.decide_every == 4
    assert "decide_every" not in Modulator("T", hidden=(16, 16)).config       # saved configs stay as they were


@pytest.mark.parametrize("kwargs, words", [({"decide_every": 0}, "decide_every"),
                                           ({"decide_every": 2, "inputs": "observation"}, "inputs='view'"),
                                           ({"decide_every": 2, "hold_steps": 4, "hold_scale": 0.1}, "hold_steps")])
def test_bad_decision_intervals_are_refused(kwargs, words):
    with pytest.raises(ConfigError, match=words):
        Modulator("T", hidden=(16, 16), **kwargs)


def test_ppo_trains_a_modulator_that_decides_every_k_steps(tiny_dataset, tmp_path):
    """``modulator.decide_every``: the trainer's env is built with the modulator's interval (its view,
    with the ``held`` part, fits the modulator), the heads learn from the decisions, and the saved
    modulator keeps its interval; a modulator given to the trainer brings its own interval to the env."""
    from adadex.train.config import CollectorConfig, ModulatorSettings, PPOConfig, TrainConfig
    from adadex.train.ppo import PPOTrainer

    tracker = tmp_path / "replay.pt"
    Tracker.replay().save(tracker)

    def config(out, every):
        return TrainConfig(dataset=str(tiny_dataset), out=str(tmp_path / out), wandb=False, progress=False,
                           eval_max_references=0, split=None,
                           ppo=PPOConfig(total_frames=256, frames_per_batch=128, minibatch_size=64, epochs=1,
                                         update_threads=1),
                           collector=CollectorConfig(worlds=4, workers=1, env_threads=1),
                           modulator=ModulatorSettings(tracker=str(tracker), channels="T", hidden=(16,),
                                                       decide_every=every))

    trainer = PPOTrainer(config("mod", K))
    assert trainer.decide_every == K
    head = trainer.policy.heads.heads[0].weight.detach().clone()
    seen = []                       # the KL-adaptive rate reads the KL at the decisions: k × the loss's mean
    adapt = trainer._adapt_lr
    trainer._adapt_lr = lambda kl: (seen.append(kl), adapt(kl))
    result = trainer.train()
    with open(tmp_path / "mod" / "metrics.csv", newline="") as f:
        logged = [float(r["kl_approx"]) for r in csv.DictReader(f) if r.get("kl_approx")]
    assert len(seen) == 2 * len(logged) and seen[0] > 0      # two minibatches an iteration
    assert sum(seen[:2]) / 2 == pytest.approx(K * logged[0], rel=1e-4)
    assert not torch.equal(head, trainer.policy.heads.heads[0].weight)
    assert Modulator.load(result["policy"]).view.decide_every == K
    up = result["updates"]          # only the decisions move: their medians are k × the loss's means
    assert up["decide_every"] == K and up["kl_median_at_decisions"] == pytest.approx(K * up["kl_median"])
    assert up["clip_fraction_median_at_decisions"] == pytest.approx(min(1.0, K * up["clip_fraction_median"]))
    given = PPOTrainer(config("given", 1), policy=Modulator("T", hidden=(16,), decide_every=2))
    env = given.transform()
    assert env[-1].layout.decide_every == 2


def test_bad_settings_are_refused_before_any_work(tmp_path):
    from adadex.train.config import ModulatorSettings

    tracker = tmp_path / "replay.pt"
    Tracker.replay().save(tracker)
    with pytest.raises(ConfigError, match=r"decide_every=4 \(modulator.decide_every\) cannot be combined with hold_steps"):
        ModulatorSettings(tracker=str(tracker), channels="T", decide_every=4, hold_steps=2, hold_scale=0.1)
    with pytest.raises(ConfigError, match="decide_every"):
        ModulatorSettings(tracker=str(tracker), channels="T", decide_every=0)
