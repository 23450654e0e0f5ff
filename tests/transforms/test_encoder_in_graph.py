"""The point-cloud encoder as a node of the policy graph (issue 45): the env's object point clouds
(:class:`ObjectPoints`), ``make_policy(..., encoder=...)`` computing the latent from them once per
episode, the same latent and the same joint targets as the env's table, and the errors that say
what is missing."""

import functools

import numpy as np
import pytest
import torch
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type, step_mdp

from adadex.envs.latent import SHIPPED_ENCODER, encoder_latent
from adadex.envs.observation import LAYOUT, OBJECT_LATENT, OBSERVATION, REFERENCE_INDEX, flat_from_tensordict
from adadex.envs.tracking import TrackingConfig, TrackingEnv
from adadex.errors import AdadexError, ConfigError, ConfigTypeError, UnknownKeyError
from adadex.eval.evaluate import evaluate
from adadex.modules.encoder import LATENT_SEED, OBJECT_POINTS, PointCloudEncoder, load_encoder, surface_points
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.transforms import ObjectPoints
from adadex.transforms.policy import ENCODED_LATENT, make_policy


@pytest.fixture(scope="module")
def tracker():
    torch.manual_seed(0)
    return Tracker(hidden=(64, 64)).freeze()


@pytest.fixture(scope="module")
def encoder():
    return PointCloudEncoder(load_encoder(SHIPPED_ENCODER)[0])


def _zero_latent(name):
    """An env latent that carries nothing: what the tracker sees must come from the encoder."""
    return np.zeros(64, dtype=np.float32)


def _env(dataset, B=3, **kw):
    return TrackingEnv(dataset, num_worlds=B, split=None, seed=3, **kw)


def _objects(env, index):
    return [env.dataset.entries[int(i)]["object"] for i in index.reshape(-1)]


def _table(env, index):
    """The shipped table's latent of each world's object, (…, 64)."""
    z = np.stack([encoder_latent(o) for o in _objects(env, index)])
    return torch.from_numpy(z).reshape(*index.shape, 64)


# -- ObjectPoints ---------------------------------------------------------------------------------

def test_object_points_are_the_tables_clouds_at_reset_and_through_steps(tiny_dataset):
    base = _env(tiny_dataset, config=TrackingConfig(window=20))
    env = TransformedEnv(base, ObjectPoints())
    check_env_specs(env)
    assert env.observation_spec[OBJECT_POINTS].shape == (3, 512, 3)
    torch.manual_seed(0)
    td = env.rollout(30, break_when_any_done=False)          # crosses the auto-reset at the window's end
    assert td["next", "truncated"].any()
    for key in [(), ("next",)]:
        points, index = td[(*key, *OBJECT_POINTS)], td[(*key, *REFERENCE_INDEX)]
        assert points.shape == (3, 30, 512, 3) and points.dtype == torch.float32
        want = torch.stack([torch.from_numpy(surface_points(o, 512, LATENT_SEED).copy())
                            for o in _objects(base, index)]).reshape(points.shape)
        assert torch.equal(points, want)          # the very cloud the latent table was computed from
    env.close()


def test_object_points_on_a_serial_env_needs_the_dataset_given(tiny_dataset):
    make = functools.partial(TrackingEnv, tiny_dataset, num_worlds=1, split=None, seed=3, nthread=0)
    env = TransformedEnv(SerialEnv(2, make), ObjectPoints(tiny_dataset, points=64))
    check_env_specs(env)
    assert env.rollout(2)[OBJECT_POINTS].shape == (2, 1, 2, 64, 3)
    env.close()
    env = TransformedEnv(SerialEnv(2, make), ObjectPoints())
    with pytest.raises(ConfigError, match=r"reference dataset .*ObjectPoints\(dataset\)"):
        env.reset()
    env.close()


def test_object_points_errors(tiny_dataset):
    with pytest.raises(ConfigError, match="points"):
        ObjectPoints(points=0)
    env = _env(tiny_dataset, B=2)
    td = env.reset()
    with pytest.raises(UnknownKeyError, match=r"\('privileged', 'reference_index'\)"):
        ObjectPoints(tiny_dataset)(td.exclude("privileged"))
    td.set(REFERENCE_INDEX, torch.tensor([0, 10_000]))
    with pytest.raises(ConfigError, match="reference index 10000 is not in"):
        ObjectPoints(tiny_dataset)(td)
    env.close()


# -- make_policy(encoder=...) ----------------------------------------------------------------------

def test_the_graphs_latent_is_the_tables(tiny_dataset, tracker, encoder):
    policy = make_policy(tracker, encoder=encoder)
    assert policy.encoder is encoder and policy.persistent
    env = TransformedEnv(_env(tiny_dataset, latent_fn=_zero_latent), policy.primer())
    check_env_specs(env)
    td = env.reset()
    assert td[OBJECT_LATENT].abs().max() == 0                      # the env's own latent is empty
    td = policy(td)
    z = td[OBJECT_LATENT]
    torch.testing.assert_close(z, _table(env.base_env, td[REFERENCE_INDEX]), rtol=0, atol=1e-5)
    assert torch.equal(td["next", *ENCODED_LATENT], z)              # carried to the next step
    # the 273-D observation is rebuilt with it: the latent slice is the encoder's, the rest the env's
    assert torch.equal(td[OBSERVATION][:, LAYOUT["latent"]], z)
    assert torch.equal(td[OBSERVATION], flat_from_tensordict(td))
    env.close()


@pytest.mark.parametrize("channels", ["none", "R+O+T"])
def test_a_rollout_with_the_encoder_gives_the_tables_joint_targets(tiny_dataset, tracker, encoder, channels):
    cfg = TrackingConfig(window=20)             # 30 steps cross an auto-reset: the encoder runs again there
    torch.manual_seed(5)
    mod = Modulator(channels, hidden=(32, 32), init_scale=1.0) if channels != "none" else None

    def run(policy, **kw):
        env = TransformedEnv(_env(tiny_dataset, config=cfg, **kw), policy.primer())
        env.set_seed(7)
        torch.manual_seed(1)
        with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
            td = env.rollout(30, policy, break_when_any_done=False)
        env.close()
        return td, env.base_env

    table, _ = run(make_policy(tracker, mod, channels=channels))
    graph, base = run(make_policy(tracker, mod, channels=channels, encoder=encoder), latent_fn=_zero_latent)
    assert graph["next", "truncated"].any()
    assert graph["next", *OBJECT_LATENT].abs().max() == 0         # the env gave no latent …
    torch.testing.assert_close(graph[OBJECT_LATENT], _table(base, graph[REFERENCE_INDEX]), rtol=0, atol=1e-5)
    for key in [("next", "proprio", "joint_target"), ("next", "proprio", "joint_pos"), OBSERVATION]:
        torch.testing.assert_close(graph[key], table[key], rtol=0, atol=1e-5)   # … and nothing changed
    if mod is not None:
        torch.testing.assert_close(graph["modulation", "sample"], table["modulation", "sample"], rtol=0, atol=1e-5)


def test_evaluate_takes_the_encoder_graph_through_its_primer(tiny_dataset, tracker, encoder):
    cfg = TrackingConfig(window=20)
    runs = [evaluate(p, tiny_dataset, split=None, env_transform=p.primer, config=cfg, progress=False, **kw)
            for p, kw in [(make_policy(tracker), {}),
                          (make_policy(tracker, encoder=encoder), {"latent_fn": _zero_latent})]]
    a, b = (r["summary"] for r in runs)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == pytest.approx(b[k], abs=1e-5, nan_ok=True), k


def test_the_encoder_runs_only_where_an_episode_starts(tiny_dataset, tracker, encoder):
    policy = make_policy(tracker, encoder=encoder)
    env = TransformedEnv(_env(tiny_dataset), policy.primer())
    td = step_mdp(env.step(policy(env.reset())))
    assert not td["is_init"].any()
    sentinel = torch.full((3, 64), 0.25)
    td.set(ENCODED_LATENT, sentinel.clone())
    assert torch.equal(policy(td)[OBJECT_LATENT], sentinel)        # later steps read the carried latent
    td = step_mdp(env.step(td))
    td.set("_reset", torch.tensor([[True], [False], [False]]))
    td.set(ENCODED_LATENT, sentinel.clone())
    td = env.reset(td)                                              # world 0 starts a new episode
    td.set(ENCODED_LATENT, sentinel.clone())
    z = policy(td)[OBJECT_LATENT]
    torch.testing.assert_close(z[0], _table(env.base_env, td[REFERENCE_INDEX])[0], rtol=0, atol=1e-5)
    assert torch.equal(z[1:], sentinel[1:])
    env.close()


def test_encoder_none_is_todays_graph(tracker):
    policy = make_policy(tracker)
    assert policy.encoder is None and not policy.persistent
    assert type(policy.primer()).__name__ == "TensorDictPrimer"
    assert [type(m).__name__ for m in policy.module] == ["_TrackerStage"]


def test_bad_input_names_what_is_missing_and_how_to_add_it(tiny_dataset, tracker, encoder):
    policy = make_policy(tracker, encoder=encoder)
    env = _env(tiny_dataset, B=2)
    with pytest.raises(UnknownKeyError, match=r"\('object', 'points'\).*env\.append_transform\(policy\.primer\(\)\)"
                                              r".*ObjectPoints") as e:
        policy(env.reset())                      # the plain env emits no point clouds
    assert isinstance(e.value, AdadexError)
    env.close()
    env = TransformedEnv(_env(tiny_dataset, B=2), ObjectPoints())       # points, but no primer
    with pytest.raises(UnknownKeyError, match=r"\('encoder', 'latent'\).*policy\.primer\(\)"):
        policy(env.reset())
    env.close()
    with pytest.raises(ConfigTypeError, match="PointCloudEncoder"):
        make_policy(tracker, encoder=torch.nn.Linear(3, 64))
