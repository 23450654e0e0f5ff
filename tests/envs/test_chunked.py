"""The chunked rollout loop that evaluation and teacher rollouts share: how references are split
into chunks, which seed each chunk's env gets, and that a seed fixes the rollouts."""

import pytest
import torch

from adadex.data.reference import ReferenceDataset
from adadex.envs.chunked import chunk_seed, chunked_rollouts
from adadex.envs.observation import OBJECT_START
from adadex.envs.randomization import Randomization
from adadex.envs.replay import replay_policy
from adadex.envs.tracking import TrackingConfig, TrackingEnv, episode_references
from adadex.errors import ConfigError

CFG = TrackingConfig(window=16)


def _equal(a, b) -> bool:
    keys = set(a.keys(True, True))
    return keys == set(b.keys(True, True)) and all(torch.equal(a[k], b[k]) for k in keys)


class _Count:
    n = 0

    def update(self, k):
        self.n += k


def test_chunks_seeds_and_draws(tiny_dataset):
    """Five episodes in chunks of two: [r0 r1] [r0 r1] [r2], in order, chunk k seeded chunk_seed(seed, k),
    each rollout the full window; a reference listed again beyond max_worlds meets a new start draw
    (the second chunk is the first one's worlds again, so the same seed would repeat its draws);
    the same seed gives the same rollouts, bit for bit, and the primer factory runs once per chunk."""
    ds = ReferenceDataset(tiny_dataset)
    r = episode_references(ds, None, CFG.window)[:3]
    refs = [r[0], r[1], r[0], r[1], r[2]]
    made = []

    def transform():
        from torchrl.envs import StepCounter
        made.append(1)
        return StepCounter()

    bar = _Count()
    kw = dict(max_worlds=2, seed=5, config=CFG, randomize=Randomization(), nthread=1)
    first = list(chunked_rollouts(replay_policy(), ds, refs, env_transform=transform, bar=bar, **kw))
    assert [c.index for c in first] == [0, 1, 2]
    assert [c.references for c in first] == [refs[0:2], refs[2:4], refs[4:5]]
    assert [c.seed for c in first] == [chunk_seed(5, k) for k in range(3)] and first[0].seed == 5
    assert len(set(c.seed for c in first)) == 3
    assert [tuple(c.rollout.batch_size) for c in first] == [(2, CFG.window - 1), (2, CFG.window - 1), (1, CFG.window - 1)]
    assert len(made) == 3 and ("next", "step_count") in first[0].rollout.keys(True)
    assert bar.n == len(refs) * (CFG.window - 1)
    # r0 and r1 again, in the same worlds: new draws, not a copy
    for w in range(2):
        assert not torch.allclose(first[0].rollout[OBJECT_START][w, 0], first[1].rollout[OBJECT_START][w, 0])
    # the first chunk draws as one env seeded `seed` does: the same references alone give the same rollout
    alone = list(chunked_rollouts(replay_policy(), ds, refs[:2], env_transform=transform, progress=False, **kw))
    assert len(alone) == 1 and _equal(alone[0].rollout, first[0].rollout)
    again = list(chunked_rollouts(replay_policy(), ds, refs, env_transform=transform, progress=False, **kw))
    assert all(_equal(a.rollout, b.rollout) for a, b in zip(first, again))
    other = list(chunked_rollouts(replay_policy(), ds, refs[:2], progress=False, **{**kw, "seed": 6}))
    assert not torch.equal(other[0].rollout[OBJECT_START], first[0].rollout[OBJECT_START])


def test_seed_rule_exploration_and_env_lifetime(tiny_dataset, monkeypatch):
    """A caller's seed rule is used as given (teacher rollouts number seeds consecutively); the rollout
    runs under the exploration type asked for, and the caller's code does not (nor under no_grad);
    each chunk's env is open while the caller holds the chunk and closed when the next is asked for."""
    import adadex.envs.chunked as chunked_module
    from tensordict.nn import TensorDictModule
    from torchrl.envs.utils import ExplorationType, exploration_type

    closed = []

    class Recording(TrackingEnv):
        def close(self, **kwargs):
            closed.append(self)
            super().close(**kwargs)

    monkeypatch.setattr(chunked_module, "TrackingEnv", Recording)
    seen = []

    def act(q):
        seen.append((exploration_type(), torch.is_grad_enabled()))
        return q

    policy = TensorDictModule(act, in_keys=[("proprio", "joint_target")], out_keys=["action"])
    refs = episode_references(ReferenceDataset(tiny_dataset), None, CFG.window)[:3]
    it = chunked_rollouts(policy, tiny_dataset, refs, max_worlds=2, seed=40, derive_seed=lambda s, k: s + k,
                          config=CFG, exploration=ExplorationType.RANDOM, progress=False, nthread=1)
    first = next(it)
    assert first.seed == 40 and isinstance(first.env, Recording) and closed == []
    assert exploration_type() != ExplorationType.RANDOM and torch.is_grad_enabled()
    second = next(it)
    assert second.seed == 41 and closed == [first.env]
    assert set(seen) == {(ExplorationType.RANDOM, False)}
    it.close()
    assert closed == [first.env, second.env]


def test_bad_arguments_name_the_setting(tiny_dataset):
    with pytest.raises(ConfigError, match="max_worlds"):
        chunked_rollouts(replay_policy(), tiny_dataset, [0], max_worlds=0)
    with pytest.raises(ConfigError, match="references"):
        chunked_rollouts(replay_policy(), tiny_dataset, [])
    with pytest.raises(ConfigError, match="num_worlds"):
        chunked_rollouts(replay_policy(), tiny_dataset, [0], num_worlds=3)
    with pytest.raises(ConfigError, match="steps"):
        chunked_rollouts(replay_policy(), tiny_dataset, [0], steps=0)


def test_fewer_steps_roll_out_the_same_draws_first_steps(tiny_dataset):
    refs = episode_references(ReferenceDataset(tiny_dataset), None, CFG.window)[:3]
    whole = [c.rollout for c in chunked_rollouts(replay_policy(), tiny_dataset, refs, seed=5, config=CFG,
                                                 progress=False, randomize=Randomization())]
    first = [c.rollout for c in chunked_rollouts(replay_policy(), tiny_dataset, refs, seed=5, config=CFG, steps=2,
                                                 progress=False, randomize=Randomization())]
    assert whole[0].shape[-1] == CFG.window - 1 and first[0].shape[-1] == 2
    assert _equal(first[0], whole[0][:, :2])
