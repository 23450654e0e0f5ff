"""Fixtures shared by the data tests."""

import pytest
import torch


@pytest.fixture(scope="module")
def one_torch_thread():
    """Batched retargeting of a few sequences gains nothing from threads; a busy second one slows it a lot."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
