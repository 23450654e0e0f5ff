"""Recurrent policies: a modulator with a recurrent core (TorchRL's GRUModule) and a user's own LSTM
tracker, carried step by step by the env and updated by PPO on whole sequences. Toy runs on the tiny
dataset."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import pytest
import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.envs import StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import LSTMModule, ProbabilisticActor, TanhNormal, ValueOperator, set_recurrent_mode

from adadex.envs.observation import OBS_DIM, OBSERVATION
from adadex.envs.tracking import TrackingEnv
from adadex.errors import ConfigError
from adadex.modules.modulator import Modulator
from adadex.modules.nets import ActorCritic, recurrent_state_shapes
from adadex.modules.tracker import Tracker
from adadex.sim.robot import NUM_JOINTS
from adadex.train.config import CollectorConfig, ModulatorSettings, PPOConfig, TrainConfig
from adadex.train.ppo import PPOTrainer
from adadex.transforms.modulation import modulation
from adadex.transforms.policy import make_policy, state_primer

CORE_STATE = ("modulator", "core_state")


def _config(dataset, out, **kw) -> TrainConfig:
    return TrainConfig(dataset=str(dataset), out=str(out), wandb=False, progress=False, eval_max_references=0,
                       ppo=PPOConfig(total_frames=512, frames_per_batch=256, minibatch_size=128, epochs=2,
                                     update_threads=1),
                       collector=CollectorConfig(worlds=8, workers=1, env_threads=1), **kw)


def test_a_recurrent_core_scores_each_sampled_action_from_the_state_it_was_sampled_in(tiny_dataset):
    """Sampled step by step (as a collector does, with an episode ending inside the rollout), the
    actions' log-probabilities come out again when TorchRL's recurrent mode reruns the sequence from
    the state stored at its first step — PPO's ratio starts at 1 — and not from a zeroed state."""
    torch.manual_seed(0)
    tracker = Tracker.replay().freeze()
    mod = Modulator("R+T", hidden=(32,), init_scale=0.5, core="gru", core_size=16)
    env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=3, split=None, seed=1),
                         modulation("R+T", tracker, view=mod.view))
    env.append_transform(state_primer(recurrent_state_shapes(mod.actor)))
    env.append_transform(StepCounter(max_steps=6))        # each world's episode ends at step 6 and restarts
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        rollout = env.rollout(10, mod.actor, break_when_any_done=False)
    env.close()
    assert rollout["is_init"][:, 6].all() and not rollout["is_init"][:, 1:6].any()
    assert rollout[CORE_STATE][:, 3].abs().sum() > 0            # mid-episode: a state to start from

    def log_prob(seq):
        with torch.no_grad(), set_recurrent_mode(True):
            return mod.actor.get_dist(seq.clone()).log_prob(seq["action"])

    seq = rollout[:, 3:]                          # starts mid-episode, crosses the restart
    assert torch.allclose(log_prob(seq), seq["action_log_prob"], atol=1e-3, rtol=1e-4)
    zeroed = seq.clone()
    zeroed[CORE_STATE][:, 0] = 0.0
    assert not torch.allclose(log_prob(zeroed)[:, :3], seq["action_log_prob"][:, :3], atol=1e-3)
    assert torch.allclose(log_prob(zeroed)[:, 3:], seq["action_log_prob"][:, 3:], atol=1e-3, rtol=1e-4)


def test_ppo_trains_a_modulator_with_a_recurrent_core(tiny_dataset, tmp_path):
    """``modulator.core=gru``: the trainer's env carries the core's state, the update reaches the GRU's
    weights, and the saved modulator runs in make_policy's graph, whose primer holds that state."""
    tracker = tmp_path / "replay.pt"
    Tracker.replay().save(tracker)
    cfg = _config(tiny_dataset, tmp_path / "mod", split=None,
                  modulator=ModulatorSettings(tracker=str(tracker), channels="R+T", hidden=(32,), core="gru",
                                              core_size=16))
    trainer = PPOTrainer(cfg)
    assert trainer.recurrent == {CORE_STATE: (1, 16)}
    gru = next(m for m in trainer.policy.actor.modules() if isinstance(m, nn.GRU))
    before = [p.detach().clone() for p in gru.parameters()]
    result = trainer.train()
    assert any(not torch.equal(a, b) for a, b in zip(before, gru.parameters()))
    with (Path(cfg.out) / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 and all(float(r["skipped_minibatches"]) == 0 for r in rows)
    loaded = Modulator.load(result["policy"])
    assert loaded.config["core"] == "gru" and loaded.config["core_size"] == 16
    policy = make_policy(Tracker.load(tracker), loaded)
    assert CORE_STATE in policy.state_shapes
    env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None), policy.primer())
    out = env.rollout(4, policy)
    env.close()
    assert out["next", *CORE_STATE].abs().sum() > 0 and torch.isfinite(out["action"]).all()


class LSTMTracker(ActorCritic):
    """A user's recurrent tracker built from TorchRL pieces alone: an LSTM over the observation, a
    TanhNormal on its output, a feed-forward critic."""

    kind = "lstm_tracker"

    def __init__(self, hidden: int = 16):
        super().__init__()
        self.config = {"hidden": hidden}
        lstm = LSTMModule(input_size=OBS_DIM, hidden_size=hidden, in_key=OBSERVATION, out_key="features")
        head = TensorDictModule(nn.Sequential(nn.Linear(hidden, 2 * NUM_JOINTS), NormalParamExtractor()),
                                in_keys=["features"], out_keys=["loc", "scale"])
        self.actor = ProbabilisticActor(TensorDictSequential(lstm, head), in_keys=["loc", "scale"],
                                        out_keys=["action"], distribution_class=TanhNormal,
                                        distribution_kwargs={"low": -0.1, "high": 0.1}, return_log_prob=True,
                                        spec=Bounded(low=-0.1, high=0.1, shape=(NUM_JOINTS,)))
        self.critic = ValueOperator(nn.Sequential(nn.Linear(OBS_DIM, 16), nn.Tanh(), nn.Linear(16, 1)),
                                    in_keys=[OBSERVATION])


def test_a_users_lstm_tracker_trains_with_its_state_in_the_env(tiny_dataset, tmp_path):
    """Any TorchRL LSTMModule/GRUModule in the policy: its state keys are primed in the collector's env
    and the run trains and saves."""
    policy = LSTMTracker()
    trainer = PPOTrainer(_config(tiny_dataset, tmp_path / "lstm", split=None), policy=policy)
    assert set(trainer.recurrent) == {"recurrent_state_h", "recurrent_state_c"}
    before = [p.detach().clone() for p in policy.actor.parameters()]
    result = trainer.train()
    assert Path(result["policy"]).is_file()
    assert any(not torch.equal(a, b) for a, b in zip(before, policy.actor.parameters()))


def test_a_recurrent_core_is_refused_where_it_cannot_work(tiny_dataset, tmp_path):
    """With per-sample bounds, the paired learner or an unknown core: one line naming the setting."""
    with pytest.raises(ConfigError, match="Modulator.core must be one of"):
        Modulator("T", hidden=(8,), core="lstm")
    with pytest.raises(ConfigError, match="cannot be combined with prior"):
        Modulator("C+T", hidden=(8,), core="gru", prior="anchor")
    tracker = tmp_path / "replay.pt"
    Tracker.replay().save(tracker)
    base = ModulatorSettings(tracker=str(tracker), channels="C+T")
    with pytest.raises(ConfigError, match=r"modulator.core.*prior"):
        dataclasses.replace(base, core="gru", prior="anchor")
    with pytest.raises(ConfigError, match=r"core_size"):
        dataclasses.replace(base, core="gru", core_size=0)
