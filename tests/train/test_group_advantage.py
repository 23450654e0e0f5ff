"""``ppo.advantage="group"``: each step credited against the other worlds of its group (common random
numbers from ``collector.group_size``), a leave-one-out baseline in place of the critic's."""

import pytest
import torch

from adadex.errors import ConfigError
from adadex.modules.tracker import Tracker
from adadex.train.config import CollectorConfig, ModulatorSettings, PPOConfig, TrainConfig
from adadex.train.ppo import PPOTrainer, group_advantage


def test_the_baseline_leaves_the_world_itself_out():
    target = torch.arange(12.0).reshape(6, 2, 1) ** 2               # 6 worlds, 2 steps
    from tensordict import TensorDict

    td = TensorDict({"value_target": target.clone(), "advantage": torch.zeros(6, 2, 1)}, batch_size=[6, 2])
    group_advantage(td, 3)
    for w in range(6):
        g = range(3 * (w // 3), 3 * (w // 3) + 3)
        others = torch.stack([target[o] for o in g if o != w]).mean(0)
        torch.testing.assert_close(td["advantage"][w], target[w] - others)
    with pytest.raises(ConfigError, match="groups of 4"):
        group_advantage(td, 4)


def test_group_advantage_needs_groups():
    with pytest.raises(ConfigError, match="collector.group_size ≥ 2"):
        TrainConfig(dataset="d", out="o", ppo=PPOConfig(advantage="group"))
    with pytest.raises(ConfigError, match="group_size=3 must divide worlds=8"):
        CollectorConfig(worlds=8, group_size=3)
    with pytest.raises(ConfigError, match="advantage must be one of"):
        PPOConfig(advantage="critic")


class _Spy(PPOTrainer):
    """Keeps each batch's advantages as the update used them."""

    def _update(self, data):
        out = super()._update(data)
        self.seen = getattr(self, "seen", []) + [data["advantage"].clone()]
        return out


def test_a_latched_gain_trains_against_its_group(tiny_dataset, tmp_path):
    """A context-free K modulator around replay, trained with groups of 4: every step's advantages sum
    to zero over each group (each world against the mean of the others), and the run finishes."""
    replay = Tracker.replay().save(tmp_path / "replay.pt")
    cfg = TrainConfig(dataset=str(tiny_dataset), out=str(tmp_path / "mod"), wandb=False, progress=False,
                      eval_max_references=0, env={"window": 32},
                      ppo=PPOConfig(total_frames=512, frames_per_batch=256, minibatch_size=128, epochs=1,
                                    update_threads=1, desired_kl=0.0, gamma=0.998, lmbda=1.0, advantage="group"),
                      collector=CollectorConfig(worlds=8, env_threads=1, group_size=4),
                      modulator=ModulatorSettings(tracker=str(replay), channels="K", hidden=(32, 32),
                                                  context_free=("K",)))
    trainer = _Spy(cfg)
    res = trainer.train()
    assert res["iterations"] == 2 and len(trainer.seen) == 2
    for adv in trainer.seen:
        sums = adv.reshape(2, 4, *adv.shape[1:]).sum(1)
        assert float(sums.abs().max()) < 1e-4 * float(adv.abs().max())
        assert float(adv.abs().max()) > 0                 # the worlds' sampled gains made them differ
