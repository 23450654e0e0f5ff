"""Train a policy you composed yourself, with every setting of the training recipes — see
train_custom_policy.yaml. Copy this file and change the module and the loss below; nothing in the
library needs editing.

    python recipes/train_custom_policy.py dataset=data/small_pg out=runs/custom

What is composed here: adadex's residual tracker actor (kinematic replay plus a learned correction,
``PolicyConfig.tracker``), a critic of its own (a LayerNorm in front of a Tanh MLP, reading the raw
observation), TorchRL's KL-penalty PPO loss in place of the clipped one, and a TorchRL ``StepCounter``
on every collector env. Writes ``out/custom_policy.pt`` (loads with ``ReplayResidualOwnCritic.load``),
``out/checkpoint.pt`` and ``out/metrics.csv``; ``out``, ``resume=true`` and ``force=true`` behave as in
the other training recipes, and unknown keys are refused.
"""

import functools

import hydra
from omegaconf import DictConfig
from torch import nn
from torchrl.envs import StepCounter
from torchrl.modules import MLP, ValueOperator
from torchrl.objectives import KLPENPPOLoss

from adadex.envs.observation import OBS_DIM, OBSERVATION
from adadex.envs.tracking import TrackingConfig
from adadex.modules.nets import ActorCritic
from adadex.train.config import PolicyConfig
from adadex.train.recipe import run, train_recipe


class ReplayResidualOwnCritic(ActorCritic):
    """adadex's residual tracker actor and a critic of its own."""

    kind = "custom_policy"            # the checkpoint's name: custom_policy.pt

    def __init__(self, hidden=(256, 256, 128), critic_hidden=(256, 256)):
        super().__init__()
        self.config = {"hidden": list(hidden), "critic_hidden": list(critic_hidden)}
        self.actor = PolicyConfig(hidden=tuple(hidden), anchor=0.0).tracker(
            max_action=TrackingConfig().max_action).actor
        self.critic = ValueOperator(nn.Sequential(nn.LayerNorm(OBS_DIM),
                                                  MLP(in_features=OBS_DIM, out_features=1,
                                                      num_cells=list(critic_hidden), activation_class=nn.Tanh)),
                                    in_keys=[OBSERVATION])


@hydra.main(config_path=".", config_name="train_custom_policy", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    return run(cfg, name="custom_policy",
               policy=ReplayResidualOwnCritic(hidden=tuple(cfg.policy.hidden)),
               loss=functools.partial(KLPENPPOLoss, dtarg=0.01, entropy_coeff=float(cfg.ppo.entropy_coef)),
               env_transforms=(functools.partial(StepCounter, max_steps=10_000),))


if __name__ == "__main__":
    train_recipe(main)
