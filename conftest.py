import os

import pytest

# Tests use at most the machine's 2 cores and no network (wandb offline). Torch gets one thread:
# the tests' networks and batches are small, and a second intra-op thread only spins against
# MuJoCo's rollout threads (an evaluation ran 4x slower with two); subprocesses inherit it.
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("OMP_NUM_THREADS", "1")


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    import torch

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


#: files whose tests take minutes on 2 cores, collected first so the two test processes
#: (pytest-xdist with ``--dist loadfile``, set in pyproject.toml) start them at once and the many
#: short files fill in around them, instead of one long file running alone at the end (longest first, as
#: the slowest-test report at the end of every run — ``--durations`` in pyproject.toml — shows them)
LONG_FILES = ("tests/train/test_ppo.py", "tests/sysid/test_payload.py", "tests/sysid/test_hidden_effects.py",
              "tests/train/test_pipeline.py", "tests/packaging/test_wheel.py", "tests/train/test_distill.py",
              "tests/sim/test_warp_backend.py", "tests/train/test_sim2real.py", "tests/sysid/test_worst_case.py")


def pytest_collection_modifyitems(config, items):
    rank = {f: i for i, f in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))     # stable: the rest keep their order


TINY_SEED = 4   # a seed whose tiny build keeps references on seen and held-out objects


@pytest.fixture(scope="session")
def tiny_build(tmp_path_factory):
    """(build report, folder) of the ``tiny`` reference dataset, built once for the whole session."""
    from adadex.data.build import build_dataset

    out = tmp_path_factory.mktemp("tiny") / "tiny"
    report = build_dataset("tiny", out, seed=TINY_SEED, progress=False)
    return report, out


@pytest.fixture(scope="session")
def tiny_dataset(tiny_build):
    """Folder of the session's ``tiny`` reference dataset."""
    return tiny_build[1]


@pytest.fixture(autouse=True)
def _doctest_names(request):
    """Docstring examples see ``tiny_dataset`` (the built tiny dataset folder) as a global, so the
    README-style snippets in central docstrings run for real; the dataset is built only when a
    doctest names it."""
    test = getattr(request.node, "dtest", None)          # set on doctest items only
    if test is not None and "tiny_dataset" in (test.docstring or ""):
        request.getfixturevalue("doctest_namespace")["tiny_dataset"] = str(request.getfixturevalue("tiny_dataset"))
