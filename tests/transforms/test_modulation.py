"""The R/O/T transforms, the tracker in the loop and make_policy — tested the way TorchRL tests its
own transforms: alone and in Compose, on SerialEnv/ParallelEnv, with a replay buffer, the inverse
path, check_env_specs for every channel subset, bounds under random inputs."""

import functools
import itertools

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from adadex.envs.observation import LAYOUT, REF_JOINT_POS, REF_OBJECT_POSE, flat_observation
from adadex.envs.tracking import TrackingConfig, TrackingEnv
from adadex.modules.channels import HAND_EDIT, ModulationConfig, ModulationLayout, entry_shape
from adadex.modules.modulator import Modulator
from adadex.modules.modulator_view import VIEW
from adadex.modules.tracker import Tracker
from adadex.quat import quat_angle_between
from adadex.transforms.modulation import (
    ActionModulation,
    FlatModulationAction,
    LatentModulation,
    ReferenceModulation,
    TrackerInTheLoop,
    modulation,
)
from adadex.transforms.policy import make_policy

SUBSETS = ["none"] + ["+".join(c) for n in (1, 2, 3) for c in itertools.combinations("ROT", n)]


@pytest.fixture(scope="module")
def tracker():
    torch.manual_seed(0)
    return Tracker(hidden=(64, 64)).freeze()


def _env(dataset, B=2, **kw):
    return TrackingEnv(dataset, num_worlds=B, split=None, seed=3, **kw)


def _raw_reference(env):
    """The base env's unedited reference at offsets 0, 1, 2, 4, 12 (float32, like the observation)."""
    base = env.base_env
    idx = base._frames_at()
    return torch.from_numpy(base._ref_q[idx]), torch.from_numpy(base._ref_obj[idx])


# -- specs ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("channels", SUBSETS)
def test_check_env_specs_for_every_channel_subset(tiny_dataset, tracker, channels):
    env = TransformedEnv(_env(tiny_dataset), modulation(channels, tracker))
    assert env.action_spec.shape == (2, ModulationLayout(channels).dim)
    check_env_specs(env)
    env.close()


@pytest.mark.parametrize("make", [ReferenceModulation, lambda: ReferenceModulation(ModulationConfig(persistent=False)),
                                  LatentModulation, ActionModulation])
def test_each_channel_alone_and_in_compose(tiny_dataset, make):
    env = TransformedEnv(_env(tiny_dataset), make())
    check_env_specs(env)
    assert "action" in env.full_action_spec.keys() and len(env.full_action_spec.keys(True, True)) > 1
    env.close()
    env = TransformedEnv(_env(tiny_dataset), Compose(ActionModulation(), make()) if not isinstance(make(), ActionModulation)
                         else Compose(make()))
    check_env_specs(env)
    env.close()


def test_modulation_needs_a_tracker():
    with pytest.raises(ValueError, match="tracker"):
        modulation("R+T", tracker=None)


# -- R --------------------------------------------------------------------------------------------

def _r_action(B, k_row=None, hand=0.0, obj=None):
    a_hand = torch.zeros(B, 4, 22)
    a_obj = torch.zeros(B, 4, 6)
    if k_row is not None:
        a_hand[:, k_row] = hand
        if obj is not None:
            a_obj[:, k_row] = torch.as_tensor(obj)
    return a_hand, a_obj


def test_persistent_reference_edit_moves_with_the_episode(tiny_dataset):
    cfg = ModulationConfig(lambda_hand=0.05, lambda_object_pos=0.02, lambda_object_rot=0.1)
    env = TransformedEnv(_env(tiny_dataset), ReferenceModulation(cfg))
    td = env.reset()
    assert (td[HAND_EDIT] == 0).all()
    # One residual at step 0 on frame t+2 (row 1 of the future rows): hand +1, object (+x, rotation about z).
    a_hand, a_obj = _r_action(2, k_row=1, hand=1.0, obj=[1.0, 0, 0, 0, 0, 1.0])
    zero = torch.zeros(2, 22)
    td.update({"action": zero, ("modulation", "ref_hand"): a_hand, ("modulation", "ref_object"): a_obj})
    out = env.step(td)["next"]
    # Frame t+2 of step 0 is frame t+1 of step 1: seen at offset 1, edited; offsets 0, 2, 4, 12 untouched.
    raw_q, raw_obj = _raw_reference(env)
    seen_q, seen_obj = out[REF_JOINT_POS], out[REF_OBJECT_POSE]
    torch.testing.assert_close(seen_q[:, 1] - raw_q[:, 1], torch.full((2, 22), 0.05), atol=1e-6, rtol=0)
    torch.testing.assert_close(seen_q[:, [0, 2, 3, 4]], raw_q[:, [0, 2, 3, 4]])
    torch.testing.assert_close(seen_obj[:, 1, 0] - raw_obj[:, 1, 0], torch.full((2,), 0.02), atol=1e-6, rtol=0)
    angle = quat_angle_between(seen_obj[:, 1, 3:], raw_obj[:, 1, 3:])
    torch.testing.assert_close(angle, torch.full((2,), 0.1), atol=1e-5, rtol=0)
    # The 273-D vector is reassembled from the edited entries.
    torch.testing.assert_close(out["observation"][:, LAYOUT["ref_joint_future"]][:, :22], seen_q[:, 1])
    # Step 1 with no new residual: the edit reaches offset 0 (and the joint error in the vector follows it).
    td = out.clone()
    td.update({"action": zero, ("modulation", "ref_hand"): torch.zeros(2, 4, 22),
               ("modulation", "ref_object"): torch.zeros(2, 4, 6)})
    out = env.step(td)["next"]
    raw_q, _ = _raw_reference(env)
    torch.testing.assert_close(out[REF_JOINT_POS][:, 0] - raw_q[:, 0], torch.full((2, 22), 0.05), atol=1e-6, rtol=0)
    torch.testing.assert_close(out[REF_JOINT_POS][:, 1:], raw_q[:, 1:])
    # Two steps later the edited frame is in the past: nothing edited is left in view.
    td = out.clone()
    td.update({"action": zero, ("modulation", "ref_hand"): torch.zeros(2, 4, 22),
               ("modulation", "ref_object"): torch.zeros(2, 4, 6)})
    out = env.step(td)["next"]
    raw_q, _ = _raw_reference(env)
    torch.testing.assert_close(out[REF_JOINT_POS], raw_q)
    env.close()


def test_edits_accumulate_and_reward_scores_the_original_reference(tiny_dataset):
    env = TransformedEnv(_env(tiny_dataset), ReferenceModulation())
    plain = _env(tiny_dataset)
    td, tp = env.reset(), plain.reset()
    zero = torch.zeros(2, 22)
    a_hand, a_obj = _r_action(2, k_row=0, hand=1.0)
    a_hand[:, 1] = 1.0                      # t+1 now and t+2 now: both land on the same frame next step
    td.update({"action": zero, ("modulation", "ref_hand"): a_hand, ("modulation", "ref_object"): a_obj})
    out = env.step(td)["next"]
    tp.set("action", zero)
    ref = plain.step(tp)["next"]
    raw_q, _ = _raw_reference(env)
    torch.testing.assert_close(out[REF_JOINT_POS][:, 0] - raw_q[:, 0], torch.full((2, 22), 0.05), atol=1e-6, rtol=0)
    torch.testing.assert_close(out[REF_JOINT_POS][:, 1] - raw_q[:, 1], torch.full((2, 22), 0.05), atol=1e-6, rtol=0)
    # Physics and reward do not see the edit (no tracker in the loop here): identical to the plain env.
    assert torch.equal(out["reward"], ref["reward"]) and torch.equal(out["proprio", "joint_pos"], ref["proprio", "joint_pos"])
    env.close()
    plain.close()


def test_per_step_reference_edit_does_not_persist(tiny_dataset, tracker):
    cfg = ModulationConfig(persistent=False)
    env = TransformedEnv(_env(tiny_dataset), ReferenceModulation(cfg))
    assert HAND_EDIT not in env.observation_spec.keys(True)
    td = env.reset()
    a_hand, a_obj = _r_action(2, k_row=0, hand=1.0)
    td.update({"action": torch.zeros(2, 22), ("modulation", "ref_hand"): a_hand, ("modulation", "ref_object"): a_obj})
    # Inverse path: the tracker would see the edit at t+1 …
    inv = env.transform.inv(td)
    torch.testing.assert_close(inv[REF_JOINT_POS][:, 1] - td[REF_JOINT_POS][:, 1], torch.full((2, 22), 0.05))
    # … but the next observation is the raw reference.
    out = env.step(td)["next"]
    raw_q, _ = _raw_reference(env)
    torch.testing.assert_close(out[REF_JOINT_POS], raw_q)
    env.close()


def test_reset_clears_the_edit_of_reset_worlds_only(tiny_dataset):
    env = TransformedEnv(_env(tiny_dataset, B=3), ReferenceModulation())
    td = env.reset()
    a_hand, a_obj = _r_action(3, k_row=3, hand=1.0)
    td.update({"action": torch.zeros(3, 22), ("modulation", "ref_hand"): a_hand, ("modulation", "ref_object"): a_obj})
    nxt = env.step(td)["next"]
    assert (nxt[HAND_EDIT][:, 11] != 0).all()          # frame t+12 → row 11 after one shift
    mask = torch.tensor([[False], [True], [False]])
    out = env.reset(nxt.clone().set("_reset", mask))
    assert (out[HAND_EDIT][1] == 0).all()
    assert torch.equal(out[HAND_EDIT][[0, 2]], nxt[HAND_EDIT][[0, 2]])
    raw_q, _ = _raw_reference(env)
    torch.testing.assert_close(out[REF_JOINT_POS][1], raw_q[1])
    env.close()


# -- O, T, the tracker in the loop ----------------------------------------------------------------

def _fake_obs(B=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)   # noqa: E731
    q = r(B, 5, 7)
    q[..., 3:] /= q[..., 3:].norm(dim=-1, keepdim=True)
    td = TensorDict({
        "proprio": {"joint_pos": r(B, 22), "link_pose": r(B, 5, 7)},
        "object": {"pose": q[:, 0].clone(), "latent": torch.tanh(r(B, 64))},
        "reference": {"hand_joint_pos": r(B, 5, 22), "object_pose": q.clone()},
        "action": r(B, 22) * 0.05}, batch_size=[B])
    td["observation"] = flat_observation(td["proprio", "joint_pos"], td["proprio", "link_pose"], td["object", "pose"],
                                         td["object", "latent"], td["reference", "hand_joint_pos"],
                                         td["reference", "object_pose"])
    return td


def test_latent_modulation_inverse_path():
    t = LatentModulation(ModulationConfig(lambda_latent=0.5))
    td = _fake_obs()
    a = torch.linspace(-2, 2, 64).expand(3, 64)     # beyond [−1, 1]: clipped
    td.set(("modulation", "latent"), a)
    out = t.inv(td)
    expected = (td["object", "latent"] + 0.5 * a.clamp(-1, 1)).clamp(-1, 1)
    torch.testing.assert_close(out["object", "latent"], expected)
    torch.testing.assert_close(out["observation"][:, LAYOUT["latent"]], expected)
    assert torch.equal(out["observation"][:, :209], td["observation"][:, :209])
    assert torch.equal(td["object", "latent"], _fake_obs()["object", "latent"])   # the input is not modified


def test_action_modulation_inverse_path_and_missing_entry():
    t = ActionModulation(ModulationConfig(action_bound=0.03))
    td = _fake_obs()
    a = torch.full((3, 22), 0.5)
    out = t.inv(td.clone().set(("modulation", "action"), a))
    torch.testing.assert_close(out["action"], td["action"] + 0.015)
    with pytest.raises(KeyError, match="modulation"):
        t.inv(td)


@settings(max_examples=40, deadline=None)
@given(scale=st.floats(0.0, 1e4), seed=st.integers(0, 2**16), bound=st.floats(0.0, 0.2),
       lam=st.floats(0.0, 0.2))
def test_every_channel_respects_its_bounds(scale, seed, bound, lam):
    cfg = ModulationConfig(lambda_hand=lam, lambda_object_pos=lam, lambda_object_rot=lam, lambda_latent=lam,
                           action_bound=bound)
    g = torch.Generator().manual_seed(seed)
    td = _fake_obs(seed=seed % 7)
    td.set(("modulation", "action"), torch.randn(3, 22, generator=g) * scale)
    td.set(("modulation", "latent"), torch.randn(3, 64, generator=g) * scale)
    td.set(("modulation", "ref_hand"), torch.randn(3, 4, 22, generator=g) * scale)
    td.set(("modulation", "ref_object"), torch.randn(3, 4, 6, generator=g) * scale)
    out = Compose(ActionModulation(cfg), LatentModulation(cfg), ReferenceModulation(cfg)).inv(td)
    tol = 1e-5
    assert ((out["action"] - td["action"]).abs() <= bound + tol).all()
    assert ((out["object", "latent"] - td["object", "latent"]).abs() <= lam + tol).all()
    assert out["object", "latent"].abs().max() <= 1.0
    dq = out[REF_JOINT_POS] - td[REF_JOINT_POS]
    assert (dq.abs() <= lam + tol).all() and (dq[:, 0] == 0).all()
    dp = out[REF_OBJECT_POSE][..., :3] - td[REF_OBJECT_POSE][..., :3]
    assert (dp.abs() <= lam + tol).all()
    angle = quat_angle_between(out[REF_OBJECT_POSE][..., 3:], td[REF_OBJECT_POSE][..., 3:])
    assert (angle <= 3 ** 0.5 * lam + 1e-3).all()
    assert torch.allclose(out[REF_OBJECT_POSE][..., 3:].norm(dim=-1), torch.ones(3, 5), atol=1e-5)
    assert (out[HAND_EDIT].abs() <= lam + tol).all()


def test_tracker_in_the_loop_is_deterministic_and_frozen(tracker):
    t = TrackerInTheLoop(tracker)
    td = _fake_obs()
    with set_exploration_type(ExplorationType.RANDOM):
        a1 = t.inv(td)["action"]
        a2 = t.inv(td)["action"]
    assert torch.equal(a1, a2)
    assert not any(p.requires_grad for p in t.parameters())


def test_flat_action_is_split_into_the_channel_entries():
    layout = ModulationLayout("R+T")
    flat = torch.randn(3, layout.dim)
    out = FlatModulationAction(layout).inv(TensorDict({"action": flat}, batch_size=[3]))
    assert "action" not in out.keys()
    assert torch.equal(out["modulation", "action"], flat[:, -22:])
    assert torch.equal(out["modulation", "ref_hand"].reshape(3, -1), flat[:, :88])


# -- training the modulator: any TorchRL loss, no gradient into the tracker -----------------------

def test_ppo_on_the_transformed_env_trains_the_modulator_only(tiny_dataset, tracker):
    torch.manual_seed(0)
    mod = Modulator("R+O+T", hidden=(32, 32))
    env = TransformedEnv(_env(tiny_dataset, B=2), modulation("R+O+T", tracker, view=mod.view))
    before = [p.clone() for p in tracker.parameters()]
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        data = env.rollout(6, mod.actor, break_when_any_done=False)
    GAE(gamma=0.99, lmbda=0.95, value_network=mod.critic)(data)
    loss_fn = ClipPPOLoss(mod.actor, mod.critic)
    for p in tracker.parameters():
        p.requires_grad_(True)        # even if someone unfreezes it, no gradient path reaches it
    losses = loss_fn(data)
    sum(v for k, v in losses.items() if k.startswith("loss_")).backward()
    assert all(p.grad is None for p in tracker.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in mod.actor.parameters())
    tracker.requires_grad_(False)
    assert all(torch.equal(a, b) for a, b in zip(before, tracker.parameters()))
    env.close()


# -- make_policy ----------------------------------------------------------------------------------

@pytest.mark.parametrize("channels", ["R+O+T", "R", "O+T", "none"])
def test_make_policy_on_the_plain_env_equals_the_transformed_env(tiny_dataset, tracker, channels):
    cfg = TrackingConfig(window=20)           # 30 steps cross an auto-reset at the window's end
    torch.manual_seed(5)
    mod = Modulator(channels, hidden=(32, 32), init_scale=1.0) if channels != "none" else None
    policy = make_policy(tracker, mod, channels=channels)

    def run(env, pol):
        env.set_seed(7)
        torch.manual_seed(1)
        with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
            return env.rollout(30, pol, break_when_any_done=False)

    a = run(TransformedEnv(_env(tiny_dataset, B=3, config=cfg), policy.primer()), policy)
    b = run(TransformedEnv(_env(tiny_dataset, B=3, config=cfg),
                           modulation(channels, tracker, view=mod.view if mod is not None else None)),
            mod.actor if mod is not None else None)
    assert a["next", "truncated"].any()
    keys = [("next", "proprio", "joint_pos"), ("next", "object", "pose"), ("next", "reward"), "observation"]
    for key in keys + ([VIEW] if mod is not None else []):      # the modulator saw the same in both
        assert torch.equal(a[key], b[key]), key
    if mod is not None:
        assert torch.equal(a["modulation", "sample"], b["action"])
        assert a["modulation", "sample"].abs().max() > 0.1       # the modulator did act


def test_make_policy_errors(tiny_dataset, tracker):
    with pytest.raises(ValueError, match="need a modulator"):
        make_policy(tracker, None, channels="R")
    with pytest.raises(ValueError, match="built for channels R"):
        make_policy(tracker, Modulator("R", hidden=(8,)), channels="R+T")
    policy = make_policy(tracker, Modulator("R", hidden=(8,)))
    env = _env(tiny_dataset)
    with pytest.raises(KeyError, match="primer"):
        policy(env.reset())
    env.close()


# -- batched envs, replay buffer ------------------------------------------------------------------

def _make_tracking_env(dataset):
    return TrackingEnv(dataset, num_worlds=1, split=None, seed=3, nthread=0)


_ALONE = {"R": lambda tracker: ReferenceModulation(), "O": lambda tracker: LatentModulation(),
          "T": lambda tracker: ActionModulation(), "R+O+T": lambda tracker: modulation("R+O+T", tracker)}


def _transformed(dataset, tracker, which):
    return TransformedEnv(_make_tracking_env(dataset), _ALONE[which](tracker))


@pytest.mark.parametrize("which", list(_ALONE))
def test_on_a_serial_env(tiny_dataset, tracker, which):
    # The transform outside the batched env, and inside each of its workers.
    outside = TransformedEnv(SerialEnv(2, lambda: _make_tracking_env(tiny_dataset)), _ALONE[which](tracker))
    inside = SerialEnv(2, functools.partial(_transformed, tiny_dataset, tracker, which))
    for env in (outside, inside):
        check_env_specs(env)
        td = env.rollout(4)
        assert td.batch_size == (2, 1, 4) and torch.isfinite(td["next", "reward"]).all()
        env.close()


@pytest.mark.parametrize("which", ["R", "R+O+T"])
def test_on_a_parallel_env_of_two_workers(tiny_dataset, tracker, which):
    outside = TransformedEnv(ParallelEnv(2, functools.partial(_make_tracking_env, str(tiny_dataset)),
                                         mp_start_method="fork"), _ALONE[which](tracker))
    inside = ParallelEnv(2, functools.partial(_transformed, str(tiny_dataset), tracker, which), mp_start_method="fork")
    for env in (outside, inside):
        try:
            check_env_specs(env)
            td = env.rollout(4)
            assert td.batch_size == (2, 1, 4) and torch.isfinite(td["next", "reward"]).all()
            if which == "R+O+T":
                assert td["action"].shape == (2, 1, 4, 198)
        finally:
            env.close()


def test_with_a_replay_buffer():
    """``ReplayBuffer.extend`` runs the inverse path: what is stored is what the env would receive."""
    for t, key, entry in [(ActionModulation(), "action", ("modulation", "action")),
                          (LatentModulation(), ("object", "latent"), ("modulation", "latent")),
                          (ReferenceModulation(), REF_JOINT_POS, ("modulation", "ref_hand"))]:
        td = _fake_obs(B=4)
        td.set(entry, torch.rand(4, *entry_shape(entry)) * 2 - 1)
        td.set(("modulation", "ref_object"), torch.rand(4, 4, 6) * 2 - 1)
        rb = ReplayBuffer(storage=LazyTensorStorage(16), transform=t, batch_size=4)
        rb.extend(td)
        stored = rb[:4]
        torch.testing.assert_close(stored[key], t.inv(td)[key])
        assert rb.sample().batch_size == (4,)
