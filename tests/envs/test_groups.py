"""Groups of worlds that share their episodes' draws (``TrackingEnv(group_size=G)``): common random
numbers, so that worlds of a group differ only in what their policy does — the comparison
``ppo.advantage="group"`` credits an action with."""

import numpy as np
import pytest
import torch

from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingConfig, TrackingEnv
from adadex.errors import ConfigError


def _env(dataset, group_size, seed=5, window=16, B=8):
    return TrackingEnv(dataset, num_worlds=B, split=None, randomize=Randomization(), seed=seed, nthread=0,
                       config=TrackingConfig(window=window), group_size=group_size)


def _zero(env):
    return env.reset().set("action", torch.zeros(*env.batch_size, 22))


def test_a_group_shares_its_draws_and_noise_and_groups_differ(tiny_dataset):
    env = _env(tiny_dataset, group_size=4)
    td = _zero(env)
    models = env.sim.models
    obs = [td["observation"]]
    for _ in range(5):
        td = env.step(td)["next"].set("action", torch.zeros(8, 22))
        obs.append(td["observation"])
    obs = torch.stack(obs, 1)                                        # [8, T, 273]
    for g in (0, 4):
        for w in range(g + 1, g + 4):
            assert models[w] is models[g]
            assert env.world_patches[w] is env.world_patches[g]
            torch.testing.assert_close(obs[w], obs[g], rtol=0, atol=0)    # same start, physics and noise
    assert not torch.equal(obs[0], obs[4])
    # the same env seed without groups: every world its own draw
    solo = _env(tiny_dataset, group_size=1)
    solo.reset()
    assert len({id(m) for m in solo.sim.models}) == 8
    env.close(), solo.close()


def test_a_group_follows_its_actions(tiny_dataset):
    """Worlds of a group on the same draws part ways only where their actions do."""
    env = _env(tiny_dataset, group_size=2, B=2)
    td = _zero(env)
    td["action"][1, 0] = 0.05                                          # world 1's first arm joint moves
    nxt = env.step(td)["next"]
    q = nxt["proprio", "joint_target"]
    assert float(q[1, 0] - q[0, 0]) == pytest.approx(0.05, abs=1e-6)   # the same noise on both worlds
    torch.testing.assert_close(q[1, 1:], q[0, 1:], rtol=0, atol=0)
    env.close()


def test_a_world_restarted_alone_draws_alone_and_ends_with_its_group(tiny_dataset):
    window = 16
    env = _env(tiny_dataset, group_size=4, window=window)
    td = _zero(env)
    for _ in range(3):
        td = env.step(td)["next"].set("action", torch.zeros(8, 22))
    before = env.sim.models[0]
    reset = torch.zeros(8, 1, dtype=torch.bool)
    reset[1] = True                                                    # world 1 alone (as after a termination)
    env.reset(td.set("_reset", reset))
    assert env.sim.models[0] is before and env.sim.models[2] is before and env.sim.models[1] is not before
    td = td.exclude("_reset")
    dones = []
    for _ in range(window - 4):                                        # the group's clock reaches the window end
        out = env.step(td.set("action", torch.zeros(8, 22)))["next"]
        dones.append(out["truncated"][:, 0].clone())
        td = out
    dones = torch.stack(dones)                                         # [steps, 8]
    assert not dones[:-1].any() and dones[-1].all()                    # world 1 too, though its episode is shorter
    env.reset(td.set("_reset", torch.ones(8, 1, dtype=torch.bool)))
    assert len({id(m) for m in env.sim.models[:4]}) == 1               # the group starts together again
    env.close()


@pytest.mark.parametrize("kwargs, says", [
    ({"group_size": 3}, "must divide num_worlds=8"),
    ({"group_size": 2, "draw": "cycle"}, "needs draw='random'"),
    ({"group_size": 0}, "group_size"),
])
def test_bad_groups_are_refused(tiny_dataset, kwargs, says):
    with pytest.raises(ConfigError, match=says):
        TrackingEnv(tiny_dataset, num_worlds=8, split=None, nthread=0, **kwargs)


def test_group_size_one_is_the_env_as_before(tiny_dataset):
    """``group_size=1`` draws exactly what the env drew before groups existed (same stream order)."""
    a = _env(tiny_dataset, group_size=1, B=4)
    b = TrackingEnv(tiny_dataset, num_worlds=4, split=None, randomize=Randomization(), seed=5, nthread=0,
                    config=TrackingConfig(window=16))
    ta, tb = a.reset(), b.reset()
    torch.testing.assert_close(ta["observation"], tb["observation"], rtol=0, atol=0)
    assert np.array_equal(a.sim.models[2].actuator_gainprm, b.sim.models[2].actuator_gainprm)
    a.close(), b.close()
