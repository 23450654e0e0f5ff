"""Object anchoring: the feed-forward's shift moves the palm onto the displaced object, fades as the
reference carries it, and an anchored tracker in the env meets a displaced object where replay misses it."""

import copy
import dataclasses
import pickle

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.envs.observation import LAYOUT, OBJECT_START, REF_OBJECT_START
from adadex.envs.randomization import Randomization
from adadex.envs.replay import replay_policy
from adadex.envs.tracking import TrackingEnv
from adadex.errors import ConfigError
from adadex.modules.anchor import ObjectAnchor
from adadex.modules.tracker import Tracker
from adadex.quat import quat_angle_between
from adadex.sim.kinematics import RobotKinematics

NEXT_REF = slice(LAYOUT["ref_joint_future"].start, LAYOUT["ref_joint_future"].start + 22)
NEXT_REF_OBJECT = slice(LAYOUT["ref_object_future"].start, LAYOUT["ref_object_future"].start + 3)


def _inputs(tiny_dataset, n=6, seed=0):
    from adadex.data.reference import ReferenceDataset

    frames = ReferenceDataset(tiny_dataset).frames
    g = torch.Generator().manual_seed(seed)
    rows = torch.randint(0, frames["hand_joint_pos"].shape[0], (n,), generator=g)
    obs = torch.zeros(n, 273)
    obs[:, NEXT_REF] = frames["hand_joint_pos"][rows].float()
    ref_start = frames["object_pose"][rows].float()
    obs[:, NEXT_REF_OBJECT] = ref_start[:, :3]          # the reference object has not moved yet
    start = ref_start.clone()
    start[:, :2] += 0.04 * (torch.rand(n, 2, generator=g) - 0.5)
    return obs, start, ref_start


def test_palm_moves_by_the_objects_offset_without_turning(tiny_dataset):
    obs, start, ref_start = _inputs(tiny_dataset)
    dq = ObjectAnchor(release=0.05)(obs, start, ref_start)
    assert (dq[:, 6:] == 0).all()                                   # the fingers keep their reference
    fk = RobotKinematics(dtype=torch.float32)
    q = obs[:, NEXT_REF]
    before, after = fk.link_poses(q)[:, 0], fk.link_poses(q + dq)[:, 0]
    moved = after[:, :3] - before[:, :3]
    wanted = torch.cat([start[:, :2] - ref_start[:, :2], torch.zeros(len(q), 1)], dim=1)
    assert (moved - wanted).norm(dim=1).max() < 0.004, (moved, wanted)
    assert quat_angle_between(after[:, 3:], before[:, 3:]).max() < 0.03


def test_iterations_place_the_palm_where_one_linearized_step_misses(tiny_dataset):
    """At a 10 cm shift one damped least-squares step misses the shifted palm by centimetres;
    three Gauss–Newton steps land within a millimetre and keep the palm's orientation."""
    obs, start, ref_start = _inputs(tiny_dataset, n=16, seed=3)
    angle = torch.linspace(0, 6.0, len(obs))
    start[:, :2] = ref_start[:, :2] + 0.10 * torch.stack([angle.cos(), angle.sin()], dim=1)
    fk = RobotKinematics(dtype=torch.float32)
    q = obs[:, NEXT_REF]
    before = fk.link_poses(q)[:, 0]
    wanted = torch.cat([start[:, :2] - ref_start[:, :2], torch.zeros(len(q), 1)], dim=1)
    miss, turn = {}, {}
    for n in (1, 3):
        after = fk.link_poses(q + ObjectAnchor(release=0.05, iterations=n)(obs, start, ref_start))[:, 0]
        miss[n] = (after[:, :3] - before[:, :3] - wanted).norm(dim=1)
        turn[n] = quat_angle_between(after[:, 3:], before[:, 3:])
    assert miss[1].mean() > 0.008, miss[1]
    assert miss[3].median() < 0.001 and miss[3].mean() < 0.25 * miss[1].mean(), miss[3]
    assert turn[3].median() < 0.005 and turn[3].mean() < turn[1].mean()


def test_anchor_fades_as_the_reference_object_travels(tiny_dataset):
    obs, start, ref_start = _inputs(tiny_dataset)
    linear, anchor = ObjectAnchor(release=0.05, iterations=1), ObjectAnchor(release=0.05)
    full = linear(obs, start, ref_start)
    fk = RobotKinematics(dtype=torch.float32)
    q = obs[:, NEXT_REF]
    wanted = torch.cat([start[:, :2] - ref_start[:, :2], torch.zeros(len(q), 1)], dim=1)
    for travel, weight in ((0.015, 1.0), (0.045, 0.5), (0.07, 0.0), (0.2, 0.0)):
        moved = obs.clone()
        moved[:, NEXT_REF_OBJECT.start + 2] += travel               # the reference lifts the object
        torch.testing.assert_close(linear(moved, start, ref_start), weight * full, atol=2e-4, rtol=1e-2)
        palm = fk.link_poses(q + anchor(moved, start, ref_start))[:, 0, :3] - fk.link_poses(q)[:, 0, :3]
        assert (palm - weight * wanted).norm(dim=1).max() < 0.004     # the palm moves by the weighted offset
    assert (anchor(obs, ref_start, ref_start) == 0).all()          # no offset, no shift


def test_a_lookahead_reads_the_reference_object_that_many_steps_ahead(tiny_dataset):
    """``lookahead=4``: the weight follows the reference object's travel at t+4 (the observation's third
    future frame), not at t+1 — the hand starts back before the reference moves the object."""
    from adadex.modules.anchor import LOOKAHEADS, ref_object_slice

    obs, start, ref_start = _inputs(tiny_dataset)
    t4 = ref_object_slice(4)
    assert LOOKAHEADS == (1, 2, 4, 12) and ref_object_slice(1) == NEXT_REF_OBJECT and t4.start == NEXT_REF_OBJECT.start + 14
    obs[:, t4] = ref_start[:, :3]                                   # at rest at t+4 too
    ahead = ObjectAnchor(release=0.05, lookahead=4, iterations=1)         # linear: the shift scales with w
    next_frame = ObjectAnchor(release=0.05, iterations=1)
    rest = ahead(obs, start, ref_start)
    torch.testing.assert_close(rest, next_frame(obs, start, ref_start))     # at rest everywhere: the same shift
    lifting = obs.clone()
    lifting[:, t4.start + 2] += 0.045                              # lifted 4.5 cm by t+4, not yet at t+1
    torch.testing.assert_close(ahead(lifting, start, ref_start), 0.5 * rest, atol=2e-4, rtol=2e-2)
    torch.testing.assert_close(next_frame(lifting, start, ref_start), rest)
    torch.testing.assert_close(ahead.weight(lifting, ref_start), torch.full((len(obs),), 0.5))


def test_reach_leaves_objects_displaced_beyond_it_alone(tiny_dataset):
    obs, start, ref_start = _inputs(tiny_dataset, n=8)
    offsets = torch.tensor([0.0, 0.03, 0.06, 0.085, 0.095, 0.12, 0.2, 0.089])
    start[:, :2] = ref_start[:, :2]
    start[:, 0] += offsets * 0.6
    start[:, 1] -= offsets * 0.8                                     # |Δ| = offsets
    limited, free = ObjectAnchor(release=0.05, reach=0.09), ObjectAnchor(release=0.05)
    dq, dq_free = limited(obs, start, ref_start), free(obs, start, ref_start)
    inside = offsets < 0.09
    torch.testing.assert_close(dq[inside], dq_free[inside])
    assert (dq[~inside] == 0).all()
    assert (dq_free[~inside].abs().amax(dim=1) > 0.01).all()        # the unlimited anchor reaches for them


def test_bad_settings():
    with pytest.raises(ValueError, match="release"):
        ObjectAnchor(release=0.0)
    with pytest.raises(ValueError, match="reach"):
        ObjectAnchor(reach=-0.1)
    with pytest.raises(ValueError, match="iterations"):
        ObjectAnchor(iterations=0)
    for bad in (3, 0, True):
        with pytest.raises(ConfigError, match=r"lookahead must be one of .*\(1, 2, 4, 12\)"):
            ObjectAnchor(lookahead=bad)
    with pytest.raises(ConfigError, match="residual"):
        Tracker(hidden=(8,), anchor=0.05)
    with pytest.raises(ConfigError, match="anchor_reach"):
        Tracker(hidden=(8,), residual=0.25, anchor_reach=0.09)
    with pytest.raises(ConfigError, match="anchor_lookahead=4"):
        Tracker(hidden=(8,), residual=0.25, anchor_lookahead=4)
    from adadex.train.config import PolicyConfig

    with pytest.raises(ConfigError, match=r"PolicyConfig.anchor_lookahead must be one of \(1, 2, 4, 12\)"):
        PolicyConfig(anchor_lookahead=3)
    with pytest.raises(ConfigError, match="anchor_lookahead=4 times the object anchor, which is off"):
        PolicyConfig(anchor=0.0, anchor_lookahead=4)


def test_untrained_anchored_tracker_is_shifted_replay_and_round_trips(tiny_dataset, tmp_path):
    obs, start, ref_start = _inputs(tiny_dataset)
    td = TensorDict({"observation": obs, ("proprio", "joint_target"): obs[:, NEXT_REF] - 0.01,
                     OBJECT_START: start, REF_OBJECT_START: ref_start}, batch_size=[len(obs)])
    tracker = Tracker(hidden=(16,), residual=0.25, anchor=0.05)
    tracker.zero_mean()
    with torch.no_grad():
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            action = tracker.actor(td.clone())["action"]
        wanted = replay_like(td) + ObjectAnchor(0.05)(obs, start, ref_start)
        torch.testing.assert_close(action, wanted, atol=1e-5, rtol=0)
    tracker.save(tmp_path / "t.pt")
    loaded = Tracker.load(tmp_path / "t.pt")
    assert loaded.config["anchor"] == 0.05 and loaded.config["anchor_reach"] == 0.0
    reaching = Tracker(hidden=(16,), residual=0.25, anchor=0.05, anchor_reach=0.03)
    reaching.save(tmp_path / "r.pt")
    anchor = Tracker.load(tmp_path / "r.pt").actor._sampling_parts[1].module.anchor
    assert anchor.reach == 0.03 and anchor.release == 0.05
    assert anchor.iterations == 3
    old = torch.load(tmp_path / "r.pt", weights_only=True)
    del old["config"]["anchor_iterations"]                       # saved before the anchor iterated
    torch.save(old, tmp_path / "old.pt")
    assert Tracker.load(tmp_path / "old.pt").actor._sampling_parts[1].module.anchor.iterations == 1
    assert "anchor_lookahead" not in reaching.config           # at its default the config reads as before it existed
    assert Tracker.load(tmp_path / "r.pt").actor._sampling_parts[1].module.anchor.lookahead == 1
    Tracker(hidden=(16,), residual=0.25, anchor=0.05, anchor_lookahead=4).save(tmp_path / "ahead.pt")
    assert Tracker.load(tmp_path / "ahead.pt").actor._sampling_parts[1].module.anchor.lookahead == 4
    # a weightless setting taken differently at load time: the same network, another reach
    wider = Tracker.load(tmp_path / "r.pt", anchor_reach=0.10)
    assert wider.actor._sampling_parts[1].module.anchor.reach == 0.10 and wider.config["anchor_reach"] == 0.10
    assert all(torch.equal(a, b) for a, b in zip(wider.state_dict().values(), reaching.state_dict().values()))
    with pytest.raises(ConfigError, match=r"no settings \['anchor_rech'\]"):
        Tracker.load(tmp_path / "r.pt", anchor_rech=0.10)
    assert set(loaded.actor.in_keys) >= {OBJECT_START, REF_OBJECT_START}
    pickle.loads(pickle.dumps(copy.deepcopy(loaded.sampling_policy())))    # what a collector worker gets


def replay_like(td):
    return td["observation"][:, NEXT_REF] - td["proprio", "joint_target"]


def test_env_reports_the_objects_start_for_the_whole_episode(tiny_dataset):
    rnd = dataclasses.replace(Randomization.off(), object_xy_std=0.05)
    env = TrackingEnv(tiny_dataset, num_worlds=4, split=None, seed=0, randomize=rnd)
    td = env.rollout(8, replay_policy(), break_when_any_done=False)
    start = td[OBJECT_START]
    torch.testing.assert_close(start[:, 0], td["object", "pose"][:, 0], rtol=0, atol=0)
    assert (start == start[:, :1]).all()                                     # fixed within the episode
    ref_start = td[REF_OBJECT_START][:, 0]
    assert (start[:, 0, :2] - ref_start[:, :2]).norm(dim=-1).max() > 0.005  # the displacement shows
    env.close()


def test_anchored_tracker_meets_a_displaced_object_where_replay_misses_it(tiny_dataset):
    """Before the reference moves the object, the hand should sit where the reference hand sits
    *relative to the object*; replay keeps it where it is relative to the world."""
    rnd = dataclasses.replace(Randomization.off(), object_xy_std=0.05)
    tracker = Tracker(hidden=(16,), residual=0.25, anchor=0.05).zero_mean()

    def relative_error(policy):
        env = TrackingEnv(tiny_dataset, num_worlds=6, split=None, seed=3, randomize=rnd)
        td = env.rollout(20, policy, break_when_any_done=False)
        env.close()
        nxt = td["next"]
        palm, obj = nxt["proprio", "link_pose"][..., 0, :3], nxt["object", "pose"][..., :3]
        ref_palm, ref_obj = nxt["reference", "hand_link_pose"][..., 0, 0, :3], nxt["reference", "object_pose"][..., 0, :3]
        still = (ref_obj - td[REF_OBJECT_START][..., :3]).norm(dim=-1) < 0.02      # reference object at rest
        err = ((palm - obj) - (ref_palm - ref_obj)).norm(dim=-1)
        return err[:, 5:][still[:, 5:]].mean(), int(still[:, 5:].sum())

    with set_exploration_type(ExplorationType.DETERMINISTIC):
        anchored, n = relative_error(tracker.actor)
    replayed, _ = relative_error(replay_policy())
    assert n > 20
    assert anchored < 0.4 * replayed and anchored < 0.02, (anchored, replayed)


def test_the_loss_reads_the_collected_bounds_instead_of_running_the_anchor(tiny_dataset, monkeypatch):
    """PPO's loss rebuilds the action distribution of collected steps: from the bounds the collecting
    policy wrote, it gets the same distribution as the full actor without the anchor's Jacobians."""
    from torchrl.objectives import ClipPPOLoss

    from adadex.modules.nets import stored_bounds_actor

    rnd = dataclasses.replace(Randomization.off(), object_xy_std=0.05)
    tracker = Tracker(hidden=(16,), residual=0.25, anchor=0.05, init_scale=0.05)
    env = TrackingEnv(tiny_dataset, num_worlds=6, split=None, seed=3, randomize=rnd)
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        td = env.rollout(10, tracker.sampling_policy(), break_when_any_done=False).reshape(-1)
    env.close()
    assert (td[OBJECT_START][:, :2] != td[REF_OBJECT_START][:, :2]).any()      # the anchor had work to do
    reading = stored_bounds_actor(tracker.actor)
    assert not {OBJECT_START, REF_OBJECT_START} & set(reading.in_keys)
    full, stored = ClipPPOLoss(tracker.actor, tracker.critic), ClipPPOLoss(reading, tracker.critic)
    assert list(full.state_dict()) == list(stored.state_dict())                 # the same checkpoints
    td["advantage"] = torch.randn(td.shape[0], 1)
    td["value_target"] = torch.randn(td.shape[0], 1)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        torch.testing.assert_close(reading.get_dist(td.clone()).deterministic_sample,
                                   tracker.actor.get_dist(td.clone()).deterministic_sample)
    torch.manual_seed(0)                        # TanhNormal's entropy is estimated by sampling
    expected = full(td.clone())
    calls = []
    monkeypatch.setattr(ObjectAnchor, "forward", lambda *a: calls.append(a))
    torch.manual_seed(0)
    got = stored(td.clone())
    assert not calls
    for key in ("loss_objective", "loss_critic", "loss_entropy"):
        torch.testing.assert_close(got[key], expected[key], rtol=1e-5, atol=1e-6)
    plain = Tracker(hidden=(16,), residual=0.25)
    assert stored_bounds_actor(Tracker(hidden=(16,)).actor).in_keys == ["observation"]
    assert set(stored_bounds_actor(plain.actor).in_keys) == {"observation", ("tracker", "low"), ("tracker", "high")}
