"""TorchRL environments: the batched tracking environment, its observation layout and reward;
importing this package registers ``adadex/Tracking-v0`` with gymnasium."""

from adadex.envs.gym import register as _register

_register()
