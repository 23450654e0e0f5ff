"""The gymnasium registration of ``adadex/Tracking-v0``, kept apart from :mod:`adadex.envs.gym` so that
``import adadex.envs`` registers the id without importing torch, TorchRL or MuJoCo: gymnasium imports
:class:`~adadex.envs.gym.TrackingGymEnv` only when ``gymnasium.make`` builds one."""

from __future__ import annotations

#: The gymnasium id of the one-world tracking environment.
ENV_ID = "adadex/Tracking-v0"


def register() -> None:
    """Register :data:`ENV_ID` with gymnasium (idempotent)."""
    import gymnasium

    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="adadex.envs.gym:TrackingGymEnv", disable_env_checker=True)
