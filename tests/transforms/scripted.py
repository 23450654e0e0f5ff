"""Helpers the channel tests share: a modulator stand-in that follows a script, and a sampled rollout
on fixed seeds (to run the policy graph and the transformed env on the same draws)."""

import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import ExplorationType, set_exploration_type


class Script(torch.nn.Module):
    """The action follows ``values`` over the episode's steps (the last one held), ``width`` entries wide."""

    def __init__(self, values, width: int):
        super().__init__()
        self.values, self.width, self.t = torch.as_tensor(values, dtype=torch.float32), width, 0

    def forward(self, observation):
        a = self.values[min(self.t, len(self.values) - 1)].expand(observation.shape[0], self.width).clone()
        self.t += 1
        return a


def scripted(values, width: int) -> TensorDictModule:
    """A policy writing ``"action"`` from :class:`Script`."""
    return TensorDictModule(Script(values, width), in_keys=["observation"], out_keys=["action"])


def sampled_rollout(env, policy, steps: int, env_seed: int = 7, torch_seed: int = 1):
    """``steps`` steps of ``policy`` sampling (``ExplorationType.RANDOM``) on fixed seeds; closes ``env``."""
    env.set_seed(env_seed)
    torch.manual_seed(torch_seed)
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        td = env.rollout(steps, policy, break_when_any_done=False)
    env.close()
    return td


def scripted_rollout(env, script, width: int, steps: int, seed: int = 3):
    """``steps`` steps of :func:`scripted` ``script`` on ``env`` (specs checked first, seeded); closes ``env``."""
    from torchrl.envs.utils import check_env_specs

    check_env_specs(env)
    env.set_seed(seed)
    with torch.no_grad():
        td = env.rollout(steps, scripted(script, width), break_when_any_done=False)
    env.close()
    return td
