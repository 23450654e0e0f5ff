import os

import pytest

# Tests use at most the machine's 2 cores and no network (wandb offline).
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("OMP_NUM_THREADS", "2")

TINY_SEED = 4   # a seed whose tiny build keeps references on seen and held-out objects


@pytest.fixture(scope="session")
def tiny_build(tmp_path_factory):
    """(build report, folder) of the ``tiny`` reference dataset, built once for the whole session."""
    import torch

    from adadex.data.build import build_dataset

    out = tmp_path_factory.mktemp("tiny") / "tiny"
    n = torch.get_num_threads()
    torch.set_num_threads(1)   # batched retargeting of a few sequences gains nothing from a busy second thread
    try:
        report = build_dataset("tiny", out, seed=TINY_SEED, progress=False)
    finally:
        torch.set_num_threads(n)
    return report, out


@pytest.fixture(scope="session")
def tiny_dataset(tiny_build):
    """Folder of the session's ``tiny`` reference dataset."""
    return tiny_build[1]
