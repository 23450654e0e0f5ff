"""Single-world gymnasium access to the tracking environment: ``gymnasium.make("adadex/Tracking-v0", …)``.

The environment is registered when :mod:`adadex.envs` is imported (or use the module form
``gymnasium.make("adadex.envs:adadex/Tracking-v0", dataset=…)``). Observations are the flat 273-D
vector, actions the 22-D joint-target change; ``info`` holds the frame's metric errors and the
reference name. For batched training use :class:`~adadex.envs.tracking.TrackingEnv` directly:
it steps all worlds in one rollout call, which this one-world wrapper cannot.

Example::

    import gymnasium, adadex.envs
    env = gymnasium.make("adadex/Tracking-v0", dataset="data/small")
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
"""

from __future__ import annotations

import gymnasium
import numpy as np
import torch

from adadex.envs.observation import OBS_DIM
from adadex.envs.tracking import TrackingConfig, TrackingEnv
from adadex.envs.frame_errors import ERROR_NAMES
from adadex.envs.registration import ENV_ID, register
from adadex.sim.robot import NUM_JOINTS


class TrackingGymEnv(gymnasium.Env):
    """One world of :class:`TrackingEnv` behind the gymnasium API (keyword arguments pass through).

    Observations are the flat (273,) float32 vector, actions (22,) float32 within
    ±``config.max_action``; ``info`` carries the frame errors, the reference index and ``unstable``.

    Args:
        dataset: the reference dataset (as :class:`TrackingEnv` takes it).
        split: ``(split name, part)`` the references are drawn from (default
            ``("unseen_trajectory", "train")``).
        config: the episode settings (:class:`TrackingConfig`).
        **kwargs: :class:`TrackingEnv`'s other keyword arguments (``seed``, ``latent_fn``, ``patch`` …);
            ``num_worlds`` is 1 and ``nthread`` 0.
    """

    metadata = {"render_modes": []}

    def __init__(self, dataset, *, split=("unseen_trajectory", "train"), config: TrackingConfig = TrackingConfig(),
                 **kwargs):
        self._env = TrackingEnv(dataset, num_worlds=1, split=split, config=config, nthread=0, **kwargs)
        high = np.full(OBS_DIM, np.inf, dtype=np.float32)
        self.observation_space = gymnasium.spaces.Box(-high, high, dtype=np.float32)
        m = np.float32(config.max_action)
        self.action_space = gymnasium.spaces.Box(-m, m, shape=(NUM_JOINTS,), dtype=np.float32)
        self._td = None

    def _info(self, td) -> dict:
        info = {k: float(td["privileged", "errors", k][0]) for k in ERROR_NAMES}
        info["reference"] = self._env.current_references[0]
        info["unstable"] = bool(td["privileged", "unstable"][0, 0])
        return info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._env.set_seed(seed)
        self._td = self._env.reset()
        return self._td["observation"][0].numpy().copy(), self._info(self._td)

    def step(self, action):
        if self._td is None:
            raise RuntimeError("call reset() before step()")
        act = torch.as_tensor(np.asarray(action, dtype=np.float32).reshape(1, NUM_JOINTS))
        td = self._env.step(self._td.set("action", act))["next"]
        self._td = td.exclude("reward", "done", "terminated", "truncated")
        return (td["observation"][0].numpy().copy(), float(td["reward"][0, 0]), bool(td["terminated"][0, 0]),
                bool(td["truncated"][0, 0]), self._info(td))

    def close(self):
        self._env.close()


__all__ = ["ENV_ID", "TrackingGymEnv", "register"]
