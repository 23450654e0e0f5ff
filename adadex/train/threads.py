"""Torch's intra-op thread count for a block of code.

Training here runs small networks beside MuJoCo's rollout threads. A second torch thread buys little
for them and costs a lot when anything else holds a core: a PPO update of the modulator took 2.2 s on
one thread and 33 s on two while another process was busy (2 cores), because each parallel region
waits for a thread the scheduler has parked.
"""

from __future__ import annotations

import contextlib

import torch


@contextlib.contextmanager
def torch_threads(n: int):
    """Torch on ``n`` threads inside the block, the previous count restored after it."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
