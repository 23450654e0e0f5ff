"""Latched choices fitted from paired rollouts (:mod:`adadex.train.paired_choice`): each arm forced on the
same episodes, the heads fitted to the better arm per episode."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import InteractionType, set_interaction_type

from adadex.data.reference import ReferenceDataset
from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingConfig, episode_references
from adadex.errors import ConfigError
from adadex.eval.evaluate import evaluate
from adadex.modules.channels import ModulationConfig, ModulationLayout
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.train.paired_choice import PairedChoiceConfig, arm_actions, check_latched, fit_paired_choice, forced
from adadex.transforms.policy import make_policy


def _act(mod, n=5):
    view = torch.randn(n, mod.view.dim)
    view[:, mod.view.slices()["phase"]] = 0.0                 # an episode's first step: nothing latched yet
    with set_interaction_type(InteractionType.DETERMINISTIC):
        return mod.actor(TensorDict({mod.obs_key: view}, [n]))["action"]


@pytest.mark.parametrize("kwargs,arm", [({"channels": "A", "focus": {"A": ["start_offset"]}}, [0.3]),
                                        ({"channels": "K", "context_free": ["K"]}, [-0.6, 0.8]),
                                        ({"channels": "A+L", "loc_bound": 2.0}, [0.9, -0.2, 0.4])])
def test_a_forced_modulator_acts_its_arm_whatever_it_reads(kwargs, arm):
    mod = Modulator(hidden=(8,), **kwargs)
    action = _act(forced(mod, torch.tensor(arm)))
    torch.testing.assert_close(action, torch.tensor(arm).expand_as(action), atol=1e-4, rtol=0)
    assert not torch.allclose(_act(mod), action)              # the original is untouched


def test_only_latched_channels_and_arms_in_range():
    with pytest.raises(ConfigError, match="channel T of A\\+T acts every step"):
        check_latched(ModulationLayout("A+T"), ModulationConfig())
    off = Modulator("A", hidden=(8,), reach_latched=False)
    with pytest.raises(ConfigError, match="reach_latched=True"):
        check_latched(off.layout, ModulationConfig(), off.config)
    with pytest.raises(ConfigError, match="reach_latched=True"):
        check_latched(ModulationLayout("A"), ModulationConfig(reach_latched=False))
    with pytest.raises(ConfigError, match="at least two arms"):
        PairedChoiceConfig(arms=(1.0,))
    with pytest.raises(ConfigError, match="holdout"):
        PairedChoiceConfig(holdout=0.95)
    with pytest.raises(ConfigError, match=r"arms\[1\]: \[1.5\] is outside"):
        arm_actions((-1.0, 1.5), 1)
    with pytest.raises(ConfigError, match=r"arms\[0\]: 1 values for a 2-entry action"):
        arm_actions(((0.5,), 1.0), 2)
    assert arm_actions((-1, (0.5, 0.25)), 2).tolist() == [[-1.0, -1.0], [0.5, 0.25]]


def test_the_fit_picks_each_episodes_better_arm(tiny_dataset):
    config = TrackingConfig(window=30)
    refs = episode_references(ReferenceDataset(tiny_dataset), None, config.window)[:6]
    tracker = Tracker.replay().freeze()
    torch.manual_seed(0)
    mod = Modulator("A", hidden=(16,), focus={"A": ["start_offset"]})
    before = _act(mod)
    report = fit_paired_choice(mod, tracker, tiny_dataset, refs, PairedChoiceConfig(repeats=3, steps=600, holdout=0.0),
                               seed=5, config=config, progress=False)
    ep = report["per_episode"]
    returns = np.asarray(ep["return"])
    assert returns.shape == (18, 2) and report["frames"] == 18 * 2 * 29 and report["step"] == 600
    # the no-reach arm is the tracker alone, on the same draws (the arms are paired through the seed)
    alone = evaluate(make_policy(tracker, None, channels="none"), tiny_dataset, split=None, references=refs * 3,
                     config=config, seed=5, randomize=Randomization(), progress=False)
    np.testing.assert_allclose(returns[:, 0], alone["per_episode"]["return"], rtol=1e-5)
    assert np.abs(returns[:, 1] - returns[:, 0]).max() > 1.0            # reaching changes the episodes
    # fitted to each episode's better arm, where one is clearly better (the offsets tell the episodes apart)
    gap = np.abs(returns[:, 1] - returns[:, 0])
    clear = gap > np.median(gap)
    assert (np.asarray(ep["pick"])[clear] == returns.argmax(1)[clear]).all()
    assert not torch.allclose(_act(mod), before)
    assert report["holdout"]["fitted"]["return"] >= max(a["return"] for a in report["holdout"]["arms"]) - 1e-6


def test_a_modulator_run_with_the_paired_learner_fits_saves_and_resumes(tiny_dataset, tmp_path):
    import json

    from adadex.train.config import CollectorConfig, ModulatorSettings, TrainConfig
    from adadex.train.ppo import train

    Tracker.replay().save(tmp_path / "replay.pt")
    refs = tuple(episode_references(ReferenceDataset(tiny_dataset), None, 30)[:4])
    m = ModulatorSettings(tracker=str(tmp_path / "replay.pt"), channels="A", hidden=(16,), focus={"A": ["start_offset"]},
                          learner="paired", paired={"repeats": 2, "steps": 40, "arms": [-1, 1]})
    cfg = TrainConfig(dataset=str(tiny_dataset), out=str(tmp_path / "run"), references=refs, env={"window": 30},
                      wandb=False, progress=False, eval_max_references=2, collector=CollectorConfig(worlds=4),
                      modulator=m)
    result = train(cfg)
    report = json.loads((tmp_path / "run" / "paired_fit.json").read_text())
    assert result["frames"] == report["frames"] == 4 * 2 * 2 * 29 and report["episodes"] == 8
    assert "eval_completion_pct" in result["eval"]
    mod = Modulator.load(result["policy"])
    assert mod.config["focus"] == {"A": ["start_offset"]}
    torch.manual_seed(0)
    assert not torch.allclose(_act(mod), _act(Modulator("A", hidden=(16,), focus={"A": ["start_offset"]})))
    stamp = (tmp_path / "run" / "paired_fit.json").stat().st_mtime_ns
    again = train(TrainConfig(**{**cfg.__dict__, "resume": True}))
    assert again["resumed"] and (tmp_path / "run" / "paired_fit.json").stat().st_mtime_ns == stamp


def test_the_paired_learner_is_refused_before_any_work(tmp_path):
    from adadex.train.config import ModulatorSettings

    Tracker.replay().save(tmp_path / "replay.pt")
    with pytest.raises(ConfigError, match="channel T of A\\+T acts every step"):
        ModulatorSettings(tracker=str(tmp_path / "replay.pt"), channels="A+T", learner="paired")
    with pytest.raises(ConfigError, match="modulator.learner"):
        ModulatorSettings(tracker=str(tmp_path / "replay.pt"), channels="A", learner="sgd")
    with pytest.raises(ConfigError, match="ModulatorSettings.paired"):
        ModulatorSettings(tracker=str(tmp_path / "replay.pt"), channels="A", paired={"rate": 1})
    with pytest.raises(ConfigError, match=r"arms\[1\]"):
        ModulatorSettings(tracker=str(tmp_path / "replay.pt"), channels="A", paired={"arms": [-1, 2]})
