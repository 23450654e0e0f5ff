"""The training layer: PPO trackers on TorchRL collectors (specialists, the vanilla-PPO baseline),
point-cloud encoder training, and what they share (configs, env factories, checkpoints, logs).

The top of the library's stack: it may import every other layer; nothing below imports it.
"""
