"""PPOTrainer with the user's own modules: a policy with its own critic, another TorchRL loss, extra env
transforms, and the refusal of a policy that does not fit the run. Toy runs: the tiny dataset, 8 worlds,
2 iterations of 256 frames, no evaluation."""

from __future__ import annotations

import csv
import dataclasses
import functools
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn
from torchrl.envs import StepCounter
from torchrl.modules import MLP, ValueOperator
from torchrl.objectives import ClipPPOLoss, KLPENPPOLoss

from adadex.envs.observation import OBS_DIM, OBSERVATION
from adadex.errors import ConfigError
from adadex.modules.modulator import Modulator
from adadex.modules.nets import ActorCritic, make_actor
from adadex.modules.tracker import Tracker
from adadex.sim.robot import NUM_JOINTS
from adadex.train.checkpoint import load_checkpoint
from adadex.train.config import CollectorConfig, ModulatorSettings, PolicyConfig, PPOConfig, TrainConfig
from adadex.train.ppo import PPOTrainer, train


def _config(dataset, out, *, frames=512, **kw) -> TrainConfig:
    return TrainConfig(dataset=str(dataset), out=str(out), wandb=False, progress=False, eval_max_references=0,
                       ppo=PPOConfig(total_frames=frames, frames_per_batch=256, minibatch_size=128, epochs=2,
                                     update_threads=1),
                       collector=CollectorConfig(worlds=8, workers=1, env_threads=1),
                       policy=PolicyConfig(hidden=(32, 32)), **kw)


def _rows(out) -> list[dict]:
    with (Path(out) / "metrics.csv").open(newline="") as f:
        return list(csv.DictReader(f))


class TanhCriticPolicy(ActorCritic):
    """A user's policy: adadex's TanhNormal actor, and a critic of its own (a Tanh MLP, no normalizer)."""

    kind = "tanh_critic"

    def __init__(self, hidden=(16,)):
        super().__init__()
        self.config = {"hidden": list(hidden)}
        self.actor = make_actor(OBSERVATION, OBS_DIM, [NUM_JOINTS], -0.1, 0.1, (32, 32), namespace="tracker",
                                init_scale=0.5)
        self.critic = ValueOperator(MLP(in_features=OBS_DIM, out_features=1, num_cells=list(hidden),
                                        activation_class=nn.Tanh), in_keys=[OBSERVATION])


def _critic_params(policy) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in policy.critic.parameters()])


def test_a_users_policy_with_its_own_critic_trains_and_resumes(tiny_dataset, tmp_path):
    torch.manual_seed(0)
    policy = TanhCriticPolicy()
    before = _critic_params(policy).clone()
    cfg = _config(tiny_dataset, tmp_path / "run")
    trainer = PPOTrainer(cfg, policy=policy)
    assert trainer.policy is policy
    res = trainer.train()
    assert res["iterations"] == 2 and res["policy"] == tmp_path / "run" / "tanh_critic.pt"
    assert not torch.equal(_critic_params(policy), before)         # the user's critic was trained
    assert res["policy"].is_file() and TanhCriticPolicy.load(res["policy"])
    # the checkpoint holds the loss (the user's actor and critic): a resumed run continues from it
    ck = load_checkpoint(tmp_path / "run")
    assert any("critic" in k for k in ck["module"])
    fresh = TanhCriticPolicy()
    resumed = PPOTrainer(_config(tiny_dataset, tmp_path / "run", resume=True), policy=fresh)
    assert resumed._resume() and resumed.iteration == 2
    torch.testing.assert_close(_critic_params(fresh), _critic_params(policy))


def _normalizers(policy):
    from adadex.modules.nets import Normalizer

    return [m for m in policy.modules() if isinstance(m, Normalizer)]


def test_a_trained_tracker_given_to_fine_tune_keeps_its_observation_statistics(tiny_dataset, tmp_path):
    """A policy whose normalizers are all fitted starts from them (fine-tuning acts as the tracker did);
    one whose normalizers are not is fitted on the first batch, as the built policy is."""
    torch.manual_seed(0)
    trained = train(_config(tiny_dataset, tmp_path / "first", frames=256))["policy"]
    tracker = Tracker.load(trained)
    stats = [(n.loc.clone(), n.scale.clone()) for n in _normalizers(tracker)]
    assert stats and all(n.fitted for n in _normalizers(tracker))
    trainer = PPOTrainer(_config(tiny_dataset, tmp_path / "again", frames=256), policy=tracker)
    assert trainer.fitted
    trainer.train()
    for n, (loc, scale) in zip(_normalizers(tracker), stats):
        torch.testing.assert_close(n.loc, loc)
        torch.testing.assert_close(n.scale, scale)
    fresh = PolicyConfig(hidden=(32, 32)).tracker()
    assert not any(n.fitted for n in _normalizers(fresh))
    other = PPOTrainer(_config(tiny_dataset, tmp_path / "fresh", frames=256), policy=fresh)
    assert not other.fitted
    other.train()
    assert all(n.fitted for n in _normalizers(fresh))


def test_a_loss_factory_replaces_clip_ppo(tiny_dataset, tmp_path):
    """KLPENPPOLoss reads the collecting policy's distribution parameters from the minibatch: the
    trainer keeps the loss's own inputs in its buffer."""
    cfg = _config(tiny_dataset, tmp_path / "klpen")
    trainer = PPOTrainer(cfg, loss=functools.partial(KLPENPPOLoss, dtarg=0.01, entropy_coeff=0.0))
    assert type(trainer.loss) is KLPENPPOLoss
    assert ("tracker", "loc") in trainer._minibatch_keys() and ("tracker", "scale") in trainer._minibatch_keys()
    res = trainer.train()
    assert res["iterations"] == 2
    rows = _rows(tmp_path / "klpen")
    assert all(r["kl"] != "" and float(r["loss_objective"]) == float(r["loss_objective"]) for r in rows)
    # the loss's state (the KL penalty's beta included) is what the checkpoint holds
    assert "beta" in load_checkpoint(tmp_path / "klpen")["module"]
    # and a partial of ClipPPOLoss with its own settings
    clip = PPOTrainer(_config(tiny_dataset, tmp_path / "clip"), loss=functools.partial(ClipPPOLoss, clip_epsilon=0.1))
    assert type(clip.loss) is ClipPPOLoss and float(clip.loss.clip_epsilon) == pytest.approx(0.1)


def test_extra_env_transforms_reach_the_collected_batch_and_the_workers(tiny_dataset, tmp_path):
    cfg = _config(tiny_dataset, tmp_path / "steps")
    trainer = PPOTrainer(cfg, env_transforms=(functools.partial(StepCounter, max_steps=5),))
    batches = []
    update = trainer._update
    trainer._update = lambda data: (batches.append(data.clone()), update(data))[1]
    trainer.train()
    assert len(batches) == 2
    steps = batches[0]["next", "step_count"]
    assert int(steps.max()) == 5 and bool(batches[0]["next", "truncated"].any())   # episodes cut at 5 steps
    assert "episode_reward" in batches[0]["next"].keys()                          # adadex's own still there
    # a worker builds its env from a pickled factory: the transform travels with it
    worker = pickle.loads(pickle.dumps(trainer.env_factory(0).for_workers(2)[1]))
    env = worker()
    try:
        assert isinstance(env.transform[-1], StepCounter) and env.transform[-1].max_steps == 5
    finally:
        env.close()
    with pytest.raises(ConfigError, match="cannot be pickled") as e:
        PPOTrainer(cfg, env_transforms=(lambda: StepCounter(),))
    assert "\n" not in str(e.value)


def test_a_policy_that_does_not_fit_the_run_is_refused_in_one_line(tiny_dataset, tmp_path):
    path = Tracker(hidden=(16,), residual=0.25).save(tmp_path / "generalist.pt")
    cfg = _config(tiny_dataset, tmp_path / "mod", modulator=ModulatorSettings(tracker=str(path), channels="R+O+T",
                                                                              hidden=(32, 32)))
    refusals = [
        (cfg, Modulator("R+T", hidden=(16,)), "writes a 134-D action, but the modulated env (channels R+O+T) takes "
                                              "a 198-D action"),
        (cfg, Tracker(hidden=(16,)), "a modulator run"),
        (_config(tiny_dataset, tmp_path / "trk"), Modulator("T", hidden=(16,)), "a tracker run"),
    ]
    for c, policy, fragment in refusals:
        with pytest.raises(ConfigError, match=re.escape(fragment)) as e:
            PPOTrainer(c, policy=policy)
        assert "\n" not in str(e.value), str(e.value)
    mod = Modulator("R+O+T", hidden=(16,))                       # the right size: taken as it is
    trainer = PPOTrainer(cfg, policy=mod)
    assert trainer.policy is mod and trainer.env_action_dim() == 198


def test_policy_config_builds_the_tracker_it_describes():
    """PolicyConfig.tracker() is the one place a tracker is built from the settings: every field arrives."""
    from adadex.train.config import PolicyConfig

    pc = PolicyConfig(hidden=(32, 16), residual=0.2, init_scale=0.1, loc_bound=4.0, anchor=0.04,
                      anchor_reach=0.12, anchor_iterations=2, anchor_lookahead=4)
    cfg = pc.tracker(max_action=0.2).config
    assert cfg["hidden"] == [32, 16] and cfg["max_action"] == 0.2
    for k in ("residual", "init_scale", "loc_bound", "anchor", "anchor_reach", "anchor_iterations", "anchor_lookahead"):
        assert cfg[k] == getattr(pc, k), k


def test_ppo_device_is_checked(tiny_dataset, tmp_path):
    """ppo.device names cpu or a CUDA device; a CUDA device torch cannot see is refused before anything runs."""
    import pytest
    import torch

    from adadex.errors import ConfigError
    from adadex.train.config import CollectorConfig, PPOConfig, TrainConfig
    from adadex.train.ppo import PPOTrainer

    for bad in ("tpu", "cuda:x", "gpu", 3):
        with pytest.raises(ConfigError, match="ppo.device"):
            PPOConfig(device=bad)
    assert PPOConfig(device="cuda:1").device == "cuda:1"
    cfg = TrainConfig(dataset=str(tiny_dataset), out=str(tmp_path / "run"), randomize=False, wandb=False,
                      progress=False, collector=CollectorConfig(worlds=2), ppo=PPOConfig(device="cuda"))
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="sees no CUDA device"):
            PPOTrainer(cfg)
    cpu = PPOTrainer(TrainConfig(dataset=str(tiny_dataset), out=str(tmp_path / "run2"), randomize=False,
                                 wandb=False, progress=False, collector=CollectorConfig(worlds=2)))
    assert cpu.device == torch.device("cpu")
    assert all(p.device.type == "cpu" for p in cpu.loss.parameters())


def test_modulator_prior_and_held_exploration_reach_the_trained_modulator(tiny_dataset, tmp_path):
    """modulator.prior / hold_steps / hold_scale / focus (and modulation.lambda_palm) build the Modulator
    trained; a focus the modulator cannot read is refused before any work, naming the setting."""
    import pytest

    from adadex.errors import ConfigError
    from adadex.modules.tracker import Tracker
    from adadex.train.config import CollectorConfig, ModulatorSettings, TrainConfig
    from adadex.train.ppo import PPOTrainer

    Tracker(hidden=(16, 16)).save(tmp_path / "tracker.pt")
    m = ModulatorSettings(tracker=str(tmp_path / "tracker.pt"), channels="C+T", hidden=(16, 16), prior="anchor",
                          hold_steps=5, hold_scale={"palm": 0.1}, modulation={"lambda_palm": 0.08},
                          focus={"C": ["start_offset", "phase"]})
    cfg = TrainConfig(dataset=str(tiny_dataset), out=str(tmp_path / "run"), randomize=False, wandb=False,
                      progress=False, collector=CollectorConfig(worlds=2), modulator=m)
    got = PPOTrainer(cfg).policy.config
    assert (got["prior"], got["hold_steps"], got["lambda_palm"]) == ("anchor", 5, 0.08)
    assert "prior_lookahead" not in got                                  # t+1, as saved priors read
    ahead = dataclasses.replace(m, modulation={"lambda_palm": 0.08, "reach_lookahead": 4})
    assert PPOTrainer(dataclasses.replace(cfg, modulator=ahead)).policy.config["prior_lookahead"] == 4
    assert got["focus"] == {"C": ["start_offset", "phase"]}
    with pytest.raises(ConfigError, match=r"modulator.focus.*\['edit'\]"):       # C+T's view has no R edit
        ModulatorSettings(tracker=str(tmp_path / "tracker.pt"), channels="C+T", focus={"C": ["edit"]})
    with pytest.raises(ConfigError, match="modulator.prior"):
        ModulatorSettings(tracker=str(tmp_path / "tracker.pt"), channels="C+T", prior="object")
    with pytest.raises(ConfigError, match="hold_scale"):
        ModulatorSettings(tracker=str(tmp_path / "tracker.pt"), channels="C+T", hold_steps=5)


def test_updates_past_the_trust_region_are_reported(tiny_dataset, tmp_path, capsys):
    """The result says how far the updates moved the policy (median KL and clip fraction over the
    iterations), and a run whose samples were mostly clipped is told so in one warning line."""
    cfg = _config(tiny_dataset, tmp_path / "fast", split=None)
    cfg = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, lr=0.01, desired_kl=0.0, epochs=4))
    result = train(cfg, policy=TanhCriticPolicy())
    rows = _rows(cfg.out)
    assert result["updates"]["iterations"] == len(rows) == 2
    assert result["updates"]["clip_fraction_median"] > 0.6
    assert result["updates"]["kl_median"] == pytest.approx(float(np.median([float(r["kl_approx"]) for r in rows])))
    err = capsys.readouterr().err
    assert "ran past PPO's trust region" in err and "ppo.desired_kl" in err
    gentle = dataclasses.replace(cfg, out=str(tmp_path / "gentle"), ppo=dataclasses.replace(cfg.ppo, lr=1e-6))
    assert train(gentle, policy=TanhCriticPolicy())["updates"]["clip_fraction_median"] < 0.6
    assert "trust region" not in capsys.readouterr().err



def test_a_finished_runs_metrics_read_back_give_the_update_medians(tmp_path):
    """A finished run continued to more frames reads its ``metrics.csv`` back: the evaluation row it
    ended with has no update statistics (blank cells), which count as missing, not as numbers."""
    from adadex.train.logs import RunLog
    from adadex.train.ppo import update_health

    log = RunLog(tmp_path, name="run", config={}, wandb=False)
    log.log(1, {"kl_approx": 0.02, "clip_fraction": 0.2, "frames": 256})
    log.log(2, {"kl_approx": 0.04, "clip_fraction": 0.4, "frames": 512})
    log.log(2, {"eval_completion_pct": 80.0, "frames": 512})
    log.close()
    resumed = RunLog(tmp_path, name="run", config={}, wandb=False, keep_until=2)
    assert any(r["kl_approx"] == "" for r in resumed.rows)
    resumed.log(3, {"kl_approx": 0.06, "clip_fraction": 0.6, "frames": 768})
    assert update_health(resumed.rows) == {"iterations": 3, "kl_median": 0.04, "clip_fraction_median": 0.4}
    resumed.close()
