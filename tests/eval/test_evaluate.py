"""The evaluation loop and the latent-smoothness measure."""

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from adadex.envs.replay import replay_policy
from adadex.envs.tracking import TrackingConfig
from adadex.eval.evaluate import evaluate
from adadex.eval.latent_smoothness import latent_smoothness, plot_latent_smoothness
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.transforms.policy import make_policy

CFG = TrackingConfig(window=24)


def test_every_reference_once_whatever_the_chunking(tiny_dataset):
    one = evaluate(replay_policy(), tiny_dataset, split=None, config=CFG, progress=False)
    chunked = evaluate(replay_policy(), tiny_dataset, split=None, config=CFG, max_worlds=2, progress=False)
    assert one["references"] == len(one["per_reference"]) >= 3
    assert one["per_reference"] == chunked["per_reference"]
    s = one["summary"]
    assert s["trajectories"] == one["references"]
    # Kinematic replay follows the hand reference closely over a short window.
    assert s["T_h"] < 5.0 and 0 <= s["completion_pct"] <= 100


def test_a_policy_that_drifts_fails(tiny_dataset):
    drift = TensorDictModule(lambda q: torch.full_like(q, 0.1), in_keys=[("proprio", "joint_pos")], out_keys=["action"])
    res = evaluate(drift, tiny_dataset, split=None, config=CFG, progress=False)
    floor = evaluate(replay_policy(), tiny_dataset, split=None, config=CFG, progress=False)
    assert res["summary"]["E_finger"] > floor["summary"]["E_finger"] + 0.1
    assert res["summary"]["completion_pct"] < floor["summary"]["completion_pct"]
    # the arm driven off its reference: the episodes end with the palm beyond its termination error
    assert res["summary"]["ended_palm_pct"] == res["summary"]["ended_pct"] > floor["summary"]["ended_palm_pct"]


def test_a_modulated_policy_evaluates_with_its_primer(tiny_dataset):
    torch.manual_seed(0)
    policy = make_policy(Tracker(hidden=(32, 32)), Modulator("R+O+T", hidden=(32, 32)))
    res = evaluate(policy, tiny_dataset, split=None, config=CFG, env_transform=policy.primer, progress=False)
    assert res["summary"]["trajectories"] == res["references"]


def test_bad_arguments(tiny_dataset):
    with pytest.raises(ValueError, match="max_worlds"):
        evaluate(replay_policy(), tiny_dataset, split=None, max_worlds=0)
    with pytest.raises(ValueError, match="episode window"):
        evaluate(replay_policy(), tiny_dataset, split=None, config=TrackingConfig(window=5000))


def _obs(n=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"observation": torch.randn(n, 273, generator=g)}, batch_size=[n])


def test_smoothness_of_known_policies():
    blind = TensorDictModule(lambda x: x[:, :22] * 2, in_keys=["observation"], out_keys=["action"])
    assert latent_smoothness(blind, _obs())["max"] == 0.0
    # Linear in the latent: a = 3·latent[:22] → ρ = 3·‖δ[:22]‖/ε ≤ 3, and its mean ≈ 3·sqrt(22/64).
    linear = TensorDictModule(lambda x: 3 * x[:, 209:231], in_keys=["observation"], out_keys=["action"])
    out = latent_smoothness(linear, _obs(200), eps=0.01, perturbations=8, seed=1)
    assert out["rho"].shape == (1600,) and out["max"] <= 3.0 + 1e-4
    assert abs(out["mean"] - 3 * (22 / 64) ** 0.5) < 0.1


def test_smoothness_is_seeded_and_checks_input(tmp_path):
    tracker = Tracker(hidden=(32, 32))
    a = latent_smoothness(tracker.actor, _obs(), seed=3)
    b = latent_smoothness(tracker.actor, _obs(), seed=3)
    c = latent_smoothness(tracker.actor, _obs(), seed=4)
    assert torch.equal(a["rho"], b["rho"]) and not torch.equal(a["rho"], c["rho"])
    with pytest.raises(ValueError, match="eps"):
        latent_smoothness(tracker.actor, _obs(), eps=0)
    with pytest.raises(KeyError, match="observation"):
        latent_smoothness(tracker.actor, TensorDict({"x": torch.zeros(2)}, batch_size=[2]))
    plot_latent_smoothness({"tracker": a, "other": c}, tmp_path / "rho.png")
    assert (tmp_path / "rho.png").read_bytes()[:4] == b"\x89PNG"


def test_chunks_beyond_max_worlds_meet_new_draws(tiny_dataset):
    """A reference listed twice, one world per chunk, under Table 3: the second chunk draws its own
    object displacement (before, every chunk repeated the first one's draws); the first chunk keeps
    the draws of an evaluation that fits in one chunk."""
    from adadex.data.reference import ReferenceDataset
    from adadex.envs.observation import OBJECT_START
    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import episode_references

    idx = episode_references(ReferenceDataset(tiny_dataset), None, CFG.window)[:1] * 2
    kw = dict(config=CFG, progress=False, randomize=Randomization(), seed=5, keep_rollouts=True)
    two = evaluate(replay_policy(), tiny_dataset, references=idx, max_worlds=1, **kw)
    starts = [td[OBJECT_START][0, 0] for td in two["rollouts"]]
    assert not torch.allclose(starts[0], starts[1])
    one = evaluate(replay_policy(), tiny_dataset, references=idx[:1], max_worlds=1, **kw)
    assert torch.equal(one["rollouts"][0][OBJECT_START][0, 0], starts[0])


def test_per_episode_results_pair_up_and_carry_the_object_measures(tiny_dataset):
    """Every episode is kept (a reference listed twice: repeats 0 and 1), with the object-centric
    measures and the return; the reference motion ``carried`` is measured on is the dataset's, the
    same the env writes into the rollout; the return–completion rank correlation is reported."""
    from adadex.data.reference import ReferenceDataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import episode_references
    from adadex.eval.evaluate import EPISODE_FIELDS, reference_motion
    from adadex.eval.metrics import from_rollout, reference_motion_from_rollout

    ds = ReferenceDataset(tiny_dataset)
    refs = episode_references(ds, None, CFG.window)[:3] * 2
    kw = dict(config=CFG, progress=False, randomize=Randomization(), seed=2, keep_rollouts=True, max_worlds=4)
    res = evaluate(replay_policy(), tiny_dataset, references=refs, **kw)
    ep = res["per_episode"]
    assert ep["reference"] == refs and ep["repeat"] == [0, 0, 0, 1, 1, 1]
    assert set(EPISODE_FIELDS) <= set(ep) and "return" in ep
    assert all(len(v) == len(refs) for v in ep.values())
    assert res["summary"]["completion_pct"] == pytest.approx(100 * sum(ep["completion"]) / len(refs))
    assert res["summary"]["object_completion_pct"] == pytest.approx(100 * sum(ep["object_completion"]) / len(refs))
    assert res["summary"]["carried_pct"] == pytest.approx(100 * sum(ep["carried"]) / len(refs))
    assert all(o <= c for o, c in zip(ep["object_completion"], ep["completion"]))
    assert all(e or not p for e, p in zip(ep["ended_early"], ep["ended_palm"]))
    assert all(e or not u for e, u in zip(ep["ended_early"], ep["ended_unstable"]))
    assert all(r or not lift for r, lift in zip(ep["reference_lifts"], ep["lifted"]))
    rho = res["return_completion_spearman"]
    assert rho["episodes"] == len(refs) and set(rho) == {"completion", "object_completion", "episodes"}
    for k, td in enumerate(res["rollouts"]):
        chunk = refs[4 * k: 4 * (k + 1)]
        assert torch.allclose(reference_motion(ds, chunk, CFG.window - 1), reference_motion_from_rollout(td))
        # read from the rollout, whether the reference lifts agrees with the dataset's where nothing ended
        own = from_rollout(td)
        for i, r in enumerate(chunk):
            if not ep["ended_early"][4 * k + i]:
                assert bool(own["reference_lifts"][i]) == ep["reference_lifts"][4 * k + i]
                assert bool(own["lifted"][i]) == ep["lifted"][4 * k + i]


def test_two_policies_meet_the_same_draws(tiny_dataset):
    """Table rows are compared episode by episode: with the same seed and reference list, a policy that
    acts otherwise meets the same start displacements (the env draws starts and per-step noise from
    two streams the actions do not touch)."""
    from adadex.data.reference import ReferenceDataset
    from adadex.envs.observation import OBJECT_START
    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import episode_references

    refs = episode_references(ReferenceDataset(tiny_dataset), None, CFG.window)[:2] * 2
    kw = dict(config=CFG, progress=False, randomize=Randomization(), seed=9, keep_rollouts=True, max_worlds=3,
              references=refs)
    drift = TensorDictModule(lambda q: torch.full_like(q, 0.05), in_keys=[("proprio", "joint_pos")],
                             out_keys=["action"])
    a = evaluate(replay_policy(), tiny_dataset, **kw)
    b = evaluate(drift, tiny_dataset, **kw)
    assert a["per_episode"]["completion"] != b["per_episode"]["completion"] or \
        a["per_episode"]["E_finger"] != b["per_episode"]["E_finger"]
    for ta, tb in zip(a["rollouts"], b["rollouts"]):
        assert torch.equal(ta[OBJECT_START][:, 0], tb[OBJECT_START][:, 0])


def test_an_episode_ended_by_unstable_physics_is_told_from_one_that_lost_its_reference(tiny_dataset):
    # a speed bound no resting object keeps under: every world's physics counts as unstable at once
    twitchy = evaluate(replay_policy(), tiny_dataset, split=None, config=TrackingConfig(window=24, max_object_speed=1e-9),
                       progress=False)
    floor = evaluate(replay_policy(), tiny_dataset, split=None, config=CFG, progress=False)
    assert twitchy["summary"]["ended_unstable_pct"] == twitchy["summary"]["ended_pct"] == 100.0
    assert all(twitchy["per_episode"]["ended_unstable"])
    assert floor["summary"]["ended_unstable_pct"] == 0.0
