"""The 273-D observation vector: Table 4's order, checked entry by entry."""

import math

import pytest
import torch
from tensordict import TensorDict

from adadex.envs.observation import (
    JOINT_POS,
    LAYOUT,
    LINK_POSE,
    OBJECT_LATENT,
    OBJECT_POSE,
    OBS_DIM,
    REF_JOINT_POS,
    REF_LINK_POSE,
    REF_OBJECT_POSE,
    REF_OFFSETS,
    flat_from_tensordict,
    flat_observation,
)
from adadex.errors import ConfigError
from adadex.quat import quat_angle


def test_layout_is_table_4():
    bounds = {name: (s.start, s.stop) for name, s in LAYOUT.items()}
    assert bounds == {"joint_pos": (0, 22), "link_pose": (22, 57), "object_pose": (57, 64),
                      "object_error": (64, 71), "ref_object_future": (71, 99), "joint_error": (99, 121),
                      "ref_joint_future": (121, 209), "latent": (209, 273)}
    assert OBS_DIM == 273 and REF_OFFSETS == (0, 1, 2, 4, 12)


def structured(B=3, seed=0):
    g = torch.Generator().manual_seed(seed)

    def quats(*shape):
        q = torch.randn(*shape, 4, generator=g, dtype=torch.float64)
        return q / q.norm(dim=-1, keepdim=True)

    def poses(*shape):
        return torch.cat([torch.randn(*shape, 3, generator=g, dtype=torch.float64), quats(*shape)], -1)

    return TensorDict({
        JOINT_POS: torch.randn(B, 22, generator=g, dtype=torch.float64), LINK_POSE: poses(B, 5),
        OBJECT_POSE: poses(B), OBJECT_LATENT: torch.randn(B, 64, generator=g, dtype=torch.float64),
        REF_JOINT_POS: torch.randn(B, 5, 22, generator=g, dtype=torch.float64), REF_LINK_POSE: poses(B, 5, 5),
        REF_OBJECT_POSE: poses(B, 5),
    }, batch_size=[B])


def test_every_entry_lands_where_table_4_says():
    td = structured()
    obs = flat_from_tensordict(td)
    assert obs.shape == (3, 273)
    assert torch.equal(obs[:, LAYOUT["joint_pos"]], td[JOINT_POS])
    assert torch.equal(obs[:, LAYOUT["link_pose"]], td[LINK_POSE].reshape(3, 35))
    assert torch.equal(obs[:, LAYOUT["object_pose"]], td[OBJECT_POSE])
    err = obs[:, LAYOUT["object_error"]]
    assert torch.allclose(err[:, :3], td[OBJECT_POSE][:, :3] - td[REF_OBJECT_POSE][:, 0, :3])
    # The quaternion part is the relative rotation: its angle is the angle between the two.
    cos = (td[OBJECT_POSE][:, 3:] * td[REF_OBJECT_POSE][:, 0, 3:]).sum(-1).abs().clamp(max=1)
    assert torch.allclose(quat_angle(err[:, 3:]), 2 * torch.acos(cos), atol=1e-6)
    assert (err[:, 3] >= 0).all()
    assert torch.equal(obs[:, LAYOUT["ref_object_future"]], td[REF_OBJECT_POSE][:, 1:].reshape(3, 28))
    assert torch.equal(obs[:, LAYOUT["joint_error"]], td[JOINT_POS] - td[REF_JOINT_POS][:, 0])
    assert torch.equal(obs[:, LAYOUT["ref_joint_future"]], td[REF_JOINT_POS][:, 1:].reshape(3, 88))
    assert torch.equal(obs[:, LAYOUT["latent"]], td[OBJECT_LATENT])


def test_perfect_tracking_zeroes_the_errors():
    td = structured()
    td[OBJECT_POSE] = td[REF_OBJECT_POSE][:, 0]
    td[JOINT_POS] = td[REF_JOINT_POS][:, 0]
    obs = flat_from_tensordict(td)
    assert torch.allclose(obs[:, LAYOUT["object_error"]], torch.tensor([0.0, 0, 0, 1, 0, 0, 0], dtype=obs.dtype))
    assert torch.allclose(obs[:, LAYOUT["joint_error"]], torch.zeros(3, 22, dtype=obs.dtype))
    td[OBJECT_POSE] = torch.cat([td[OBJECT_POSE][:, :3], -td[OBJECT_POSE][:, 3:]], -1)   # q ≡ −q
    assert torch.allclose(flat_from_tensordict(td)[:, LAYOUT["object_error"]][:, 3:],
                          torch.tensor([1.0, 0, 0, 0], dtype=obs.dtype))


def test_extra_batch_dims_and_bad_shapes():
    td = structured(B=6).reshape(2, 3)
    assert flat_from_tensordict(td).shape == (2, 3, 273)
    td = structured()
    with pytest.raises(ValueError, match=r"ref_joint_pos: expected shape \(3, 5, 22\)"):
        flat_observation(td[JOINT_POS], td[LINK_POSE], td[OBJECT_POSE], td[OBJECT_LATENT],
                         td[REF_JOINT_POS][:, :4], td[REF_OBJECT_POSE])
    with pytest.raises(ValueError, match="latent"):
        flat_observation(td[JOINT_POS], td[LINK_POSE], td[OBJECT_POSE], td[OBJECT_LATENT][:, :32],
                         td[REF_JOINT_POS], td[REF_OBJECT_POSE])
    assert math.isfinite(float(flat_from_tensordict(td).sum()))


def test_reward_with_and_without_precomputed_errors():
    from adadex.envs.reward import RewardConfig, tracking_reward
    from adadex.envs.frame_errors import frame_errors

    td = structured(B=4, seed=3)
    q, link, obj = td[JOINT_POS], td[LINK_POSE], td[OBJECT_POSE]
    rq, rlink, robj = td[REF_JOINT_POS][:, 0], td[REF_LINK_POSE][:, 0], td[REF_OBJECT_POSE][:, 0]
    kw = dict(joint_pos=q, link_pose=link, object_pose=obj, ref_joint_pos=rq, ref_link_pose=rlink, ref_object_pose=robj)
    r1, _ = tracking_reward(RewardConfig(), **kw)
    r2, _ = tracking_reward(RewardConfig(), **kw, errors=frame_errors(obj, robj, link[:, 0], rlink[:, 0], q, rq))
    assert torch.allclose(r1, r2)
    # Perfect tracking earns the full bonus and no penalty but the proximity term.
    perfect, terms = tracking_reward(RewardConfig(), joint_pos=rq, link_pose=rlink, object_pose=robj, ref_joint_pos=rq,
                                     ref_link_pose=rlink, ref_object_pose=robj)
    assert torch.allclose(terms["bonus"], torch.ones(4, dtype=perfect.dtype))
    assert torch.allclose(terms["tracking"], torch.zeros(4, dtype=perfect.dtype), atol=1e-6)


def _reference_at_origin(B: int):
    """(joints, link poses, object pose) of a reference with everything at the origin, unrotated."""
    rlink = torch.zeros(B, 5, 7)
    rlink[..., 3] = 1.0
    robj = torch.zeros(B, 7)
    robj[:, 3] = 1.0
    return torch.zeros(B, 22), rlink, robj


def test_object_frame_hand_tracking_rewards_meeting_a_displaced_object():
    """With ``object_frame=1``, a hand that follows a displaced object in a contact phase tracks
    perfectly (only the object terms see the displacement); far from contact, and with
    ``object_frame=0`` (the world frame), the same hand is charged for the displacement."""
    from adadex.envs.reward import RewardConfig, tracking_reward

    B = 2
    rq, rlink, robj = _reference_at_origin(B)
    rlink[0, :, 0] = 0.05          # world 0: reference hand 5 cm from its object (contact phase)
    rlink[1, :, 0] = 0.40          # world 1: 40 cm away (approach)
    shift = torch.tensor([0.06, -0.03, 0.0])
    link, obj = rlink.clone(), robj.clone()
    link[..., :3] += shift
    obj[:, :3] += shift
    kw = dict(joint_pos=rq, link_pose=link, object_pose=obj, ref_joint_pos=rq, ref_link_pose=rlink,
              ref_object_pose=robj)
    _, world = tracking_reward(RewardConfig(object_frame=0.0), **kw)
    _, rel = tracking_reward(RewardConfig(object_frame=1.0), **kw)
    _, half = tracking_reward(RewardConfig(object_frame=0.5), **kw)
    moved = float(shift.norm())
    assert torch.allclose(world["tracking"], torch.full((B,), 2 * moved), atol=1e-6)   # palm + mean fingertip
    assert float(rel["tracking"][0]) < 1e-6 and abs(float(rel["tracking"][1]) - 2 * moved) < 1e-6
    assert abs(float(half["tracking"][0]) - moved) < 1e-6
    assert torch.equal(rel["goal"], world["goal"])        # the object's own error is charged either way
    with pytest.raises(ConfigError, match="object_frame"):
        RewardConfig(object_frame=1.5)


def _paid_per_frame(offsets, weights: dict, test):
    """Palm and object moved together by ``offsets`` (m, one world each) from a reference at the
    origin: (the frames ``test`` passes, the reward with ``weights`` minus the default one, its terms)."""
    from adadex.envs.frame_errors import frame_errors
    from adadex.envs.reward import RewardConfig, tracking_reward

    rq, rlink, robj = _reference_at_origin(len(offsets))
    link, obj = rlink.clone(), robj.clone()
    off = torch.tensor(offsets)
    link[..., 0] += off[:, None]
    obj[:, 0] += off
    kw = dict(joint_pos=rq, link_pose=link, object_pose=obj, ref_joint_pos=rq, ref_link_pose=rlink,
              ref_object_pose=robj)
    base, _ = tracking_reward(RewardConfig(), **kw)
    paid, terms = tracking_reward(RewardConfig(**weights), **kw)
    return test(frame_errors(obj, robj, link[:, 0], rlink[:, 0], rq, rq)), paid - base, terms


def test_success_term_pays_for_the_frames_completion_counts():
    """``w_success`` adds exactly its weight on the frames that meet the paper's success thresholds
    (world frame: an object and palm both 12 cm off fail, 8 cm off pass) and nothing elsewhere."""
    from adadex.envs.frame_errors import frame_success
    from adadex.envs.reward import RewardConfig

    ok, extra, terms = _paid_per_frame([0.0, 0.08, 0.12], {"w_success": 2.5}, frame_success)
    assert ok.tolist() == [True, True, False]
    assert torch.equal(terms["success"], ok.float())
    assert torch.allclose(extra, 2.5 * ok.float())
    with pytest.raises(ConfigError, match="w_success"):
        RewardConfig(w_success=float("nan"))


def test_object_success_term_pays_only_with_the_object_within_5_cm():
    """``w_object_success`` pays on the frames that pass the paper's thresholds with the object within
    5 cm: the frame 8 cm off passes the paper's test and fails this one."""
    from adadex.envs.frame_errors import object_success

    ok, extra, terms = _paid_per_frame([0.03, 0.08, 0.12], {"w_object_success": 3.0}, object_success)
    assert ok.tolist() == [True, False, False]
    assert torch.equal(terms["object_success"], ok.float())
    assert torch.allclose(extra, 3.0 * ok.float())
