"""Teacher rollouts and evaluation run one loop (adadex.envs.chunked.chunked_rollouts): for the same
policy, references and env seed they run the same trajectories, step for step.

They legitimately differ in two ways, neither tested as equal: evaluate may sample (``sample=True``;
teacher rollouts are always deterministic), and within one call the two number their chunk seeds
differently (teacher rollouts: ``seed + k`` over all teachers; evaluate: ``chunk_seed(seed, k)``), so a
teacher chunk ``k`` is reproduced by evaluating that chunk's references with ``seed=seed + k``."""

from __future__ import annotations

import torch

from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingConfig
from adadex.eval.evaluate import evaluate
from adadex.modules.nets import GaussianHeads
from adadex.modules.tracker import Tracker
from adadex.train.rollouts import load_rollouts, teacher_rollouts

CFG = TrackingConfig(window=24)
REFS = [1, 2, 5]
SEED, EPISODES = 3, 2                  # two chunks of three worlds: env seeds 3 and 4


def _teacher() -> Tracker:
    """An untrained residual tracker whose correction head is scaled up (as in test_distill): replay
    plus an observation-dependent correction, so its actions depend on what it observes."""
    torch.manual_seed(0)
    t = Tracker(hidden=(32, 32), residual=0.25)
    head = next(m for m in t.modules() if isinstance(m, GaussianHeads)).heads[0]
    with torch.no_grad():
        head.weight.mul_(100.0)
    return t


def test_teacher_rollouts_store_the_trajectories_evaluate_runs(tiny_dataset, tmp_path):
    teacher = _teacher()
    info = teacher_rollouts({teacher: REFS}, tiny_dataset, tmp_path / "r", episodes_per_reference=EPISODES, seed=SEED,
                            max_worlds=len(REFS), config=CFG, criterion="completion>=0.5", nthread=1, progress=False)
    data = (lambda b: b[0:len(b)])(load_rollouts(tmp_path / "r"))
    keys = [k if isinstance(k, str) else tuple(k) for k in info["keys"]] + ["action"]
    compared = 0
    for k in range(EPISODES):
        res = evaluate(teacher.actor, tiny_dataset, split=None, references=REFS, max_worlds=len(REFS), config=CFG,
                       randomize=Randomization(), seed=SEED + k, nthread=1, progress=False, keep_rollouts=True)
        td = res["rollouts"][0]
        for w in range(len(REFS)):
            rows = data["episode"] == k * len(REFS) + w
            kept = res["per_episode"]["completion"][w] >= 0.5
            assert bool(rows.any()) == kept, (k, w)
            if not kept:
                continue
            order = data["t"][rows].argsort()
            n = int(rows.sum())                 # the steps up to the first done, all of them if none
            assert data["t"][rows][order].tolist() == list(range(n))
            assert set(data["reference"][rows].tolist()) == {REFS[w]}
            for key in keys:
                assert torch.equal(data[key][rows][order], td[key][w, :n]), (k, w, key)
            compared += 1
    assert compared > 0 and compared == info["episodes_kept"]
