"""The paper's metrics on hand-computed examples and edge cases."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from adadex.eval.metrics import (
    ERROR_NAMES,
    Thresholds,
    frame_errors,
    frame_success,
    from_rollout,
    summarize,
    trajectory_metrics,
)
from adadex.errors import ArrayError
from adadex.eval.evaluate import format_summary
from adadex.quat import quat_angle, quat_diff, quat_mul

IDENTITY = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)


def about_z(angle: float) -> torch.Tensor:
    return torch.tensor([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)], dtype=torch.float64)


def pose(x, y, z, q=IDENTITY) -> torch.Tensor:
    return torch.cat([torch.tensor([x, y, z], dtype=torch.float64), q])


def test_frame_errors_hand_computed():
    obj, ref_obj = pose(0.3, 0.0, 0.1, about_z(0.3)), pose(0.0, 0.4, 0.1)       # 0.5 m off, 0.3 rad
    palm, ref_palm = pose(0.1, 0.1, 0.2), pose(0.1, 0.1, 0.23, about_z(-1.0))   # 3 cm off, 1 rad
    q, ref_q = torch.zeros(22, dtype=torch.float64), torch.zeros(22, dtype=torch.float64)
    q[0] = 5.0                    # an arm joint: not a finger, must not count
    q[6:10] = 0.4                 # four of the 16 finger joints off by 0.4 → mean 0.1
    e = frame_errors(obj, ref_obj, palm, ref_palm, q, ref_q)
    assert e["T_o"].item() == pytest.approx(0.5)
    assert e["R_o"].item() == pytest.approx(0.3)
    assert e["T_h"].item() == pytest.approx(0.03)
    assert e["R_h"].item() == pytest.approx(1.0)
    assert e["E_finger"].item() == pytest.approx(0.1)


def test_quaternion_sign_flip_is_the_same_rotation():
    a = about_z(0.7)
    assert quat_angle(quat_diff(a, IDENTITY)).item() == pytest.approx(0.7)
    assert quat_angle(quat_diff(-a, IDENTITY)).item() == pytest.approx(0.7)
    assert quat_angle(quat_diff(a, -a)).item() == pytest.approx(0.0, abs=1e-7)
    e = frame_errors(pose(0, 0, 0, -a), pose(0, 0, 0, a), pose(0, 0, 0), pose(0, 0, 0),
                     torch.zeros(22), torch.zeros(22))
    assert e["R_o"].item() == pytest.approx(0.0, abs=1e-7)


def test_quat_diff_is_the_relative_rotation():
    a, b = about_z(0.9), about_z(0.2)
    d = quat_diff(a, b)                              # a = d ⊗ b
    assert torch.allclose(quat_mul(d, b), a)
    assert quat_angle(d).item() == pytest.approx(0.7)
    assert d[0] >= 0


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-1, 1, allow_nan=False), min_size=8, max_size=8))
def test_angle_is_symmetric_and_in_range(v):
    a = torch.tensor(v[:4], dtype=torch.float64)
    b = torch.tensor(v[4:], dtype=torch.float64)
    if a.norm() < 1e-3 or b.norm() < 1e-3:
        return
    a, b = a / a.norm(), b / b.norm()
    ab, ba = quat_angle(quat_diff(a, b)), quat_angle(quat_diff(b, a))
    assert 0.0 <= ab.item() <= math.pi + 1e-9
    assert ab.item() == pytest.approx(ba.item(), abs=1e-6)


def errors_from(values: dict, B=1, T=1):
    return {k: torch.full((B, T), float(values.get(k, 0.0)), dtype=torch.float64) for k in ERROR_NAMES}


@pytest.mark.parametrize("values, ok", [
    ({}, True),
    ({"T_o": 0.10, "T_h": 0.10}, True),                     # 0.5·10 + 0.5·10 = 10 cm: on the threshold
    ({"T_o": 0.15, "T_h": 0.06}, False),                    # 10.5 cm
    ({"T_o": 0.19, "T_h": 0.0}, True),                      # 9.5 cm: the average counts, not each
    ({"R_o": math.radians(100), "R_h": math.radians(20)}, True),    # 60°
    ({"R_o": math.radians(100), "R_h": math.radians(21)}, False),
    ({"E_finger": math.radians(40)}, True),
    ({"E_finger": math.radians(41)}, False),
])
def test_thresholds(values, ok):
    assert bool(frame_success(errors_from(values))[0, 0]) is ok


def test_mean_error_and_completion_differ():
    # Trajectory 0: 4 frames, one terrible frame → mean fails (T_o mean 0.26), completion 3/4.
    # Trajectory 1: every frame slightly over a threshold → mean fails, completion 0.
    # Trajectory 2: half the frames over, half well under → mean succeeds, completion 1/2.
    e = errors_from({}, B=3, T=4)
    e["T_o"][0] = torch.tensor([0.0, 0.0, 0.0, 1.04])
    e["E_finger"][1] = math.radians(41)
    e["T_h"][2] = torch.tensor([0.0, 0.0, 0.12, 0.12])
    e["T_o"][2] = torch.tensor([0.0, 0.0, 0.12, 0.12])
    m = trajectory_metrics(e)
    assert m["T_o"].tolist() == pytest.approx([0.26, 0.0, 0.06])
    assert m["success_mean_error"].tolist() == [False, False, True]
    assert m["completion"].tolist() == pytest.approx([0.75, 0.0, 0.5])
    s = summarize(m)
    assert s["success_mean_error_pct"] == pytest.approx(100 / 3)
    assert s["completion_pct"] == pytest.approx(100 * 1.25 / 3)
    assert s["T_o"] == pytest.approx(100 * 0.32 / 3)      # cm


def test_truncated_and_empty_trajectories():
    e = errors_from({}, B=3, T=5)
    valid = torch.tensor([[1, 1, 1, 1, 1], [1, 1, 0, 0, 0], [0, 0, 0, 0, 0]], dtype=torch.bool)
    m = trajectory_metrics(e, valid=valid, lengths=torch.tensor([5, 5, 5]))
    assert m["frames"].tolist() == [5, 2, 0]
    assert m["ended_early"].tolist() == [False, True, True]
    assert m["success_mean_error"].tolist() == [True, False, False]   # ending early is not success
    assert m["completion"].tolist() == pytest.approx([1.0, 0.4, 0.0])  # frames never reached fail
    assert m["empty"].tolist() == [False, False, True] and math.isnan(m["T_o"][2])
    s = summarize(m)
    assert s["trajectories"] == 2 and s["empty"] == 1
    assert s["completion_pct"] == pytest.approx(70.0)
    assert summarize(trajectory_metrics(e, valid=torch.zeros(3, 5, dtype=torch.bool)))["trajectories"] == 0


def test_lost_frames_are_charged_to_the_first_test_they_fail_and_sum_with_completion_to_one():
    # 6 frames a trajectory should track; trajectory 1 ends after 4. Each failing frame is charged once:
    # to position if it fails that test (whatever else it fails), else rotation, else fingers.
    e = errors_from({}, B=2, T=6)
    e["T_o"][0, 0] = 0.5                                  # position (and rotation below): position
    e["R_o"][0, 0] = 3.0
    e["R_o"][0, 1] = 3.0                                  # rotation alone
    e["E_finger"][0, 2] = 1.0                             # fingers alone
    e["R_o"][0, 3] = 3.0                                  # rotation and fingers: rotation
    e["E_finger"][0, 3] = 1.0
    e["T_h"][1, 1] = 0.5                                  # position
    valid = torch.ones(2, 6, dtype=torch.bool)
    valid[1, 4:] = False
    m = trajectory_metrics(e, valid=valid, lengths=torch.tensor([6, 6]))
    assert m["lost_position"].tolist() == pytest.approx([1 / 6, 1 / 6])
    assert m["lost_rotation"].tolist() == pytest.approx([2 / 6, 0.0])
    assert m["lost_finger"].tolist() == pytest.approx([1 / 6, 0.0])
    assert m["lost_after_end"].tolist() == pytest.approx([0.0, 2 / 6])
    total = m["completion"] + m["lost_position"] + m["lost_rotation"] + m["lost_finger"] + m["lost_after_end"]
    assert total.tolist() == pytest.approx([1.0, 1.0])
    s = summarize(m)
    assert s["lost_rotation_pct"] == pytest.approx(100 / 6) and s["lost_after_end_pct"] == pytest.approx(100 / 6)
    assert format_summary(s).splitlines()[3] == ("frames lost: position test 16.7 %, rotation 16.7 %, fingers 8.3 %, "
                                                 "after the episode ended 16.7 %")



def test_why_episodes_end_palm_beyond_its_limit_unstable_physics_and_whether_the_object_was_lifted():
    # 4 trajectories of 5 frames: 0 tracked to the end, 1 ends with the palm 30 cm off, 2 ends with the
    # object off (palm fine), 3 ends after the palm came back within the limit (its last frame decides),
    # on a step whose physics went unstable; 0 was flagged unstable on a frame without ending (not counted)
    e = errors_from({}, B=4, T=5)
    valid = torch.ones(4, 5, dtype=torch.bool)
    valid[1, 3:] = valid[2, 2:] = valid[3, 4:] = False
    e["T_h"][1, 2] = 0.30
    e["T_o"][2, 1] = 0.30
    e["T_h"][3, 1] = 0.30
    # the reference raises objects 0, 1 and 3 by 10, 4 and 2 cm; the objects rise 3.1, 2.1, 5 and 1.5 cm,
    # object 1's 2.1 cm (≥ half its reference's 4 cm) on a frame after its episode ended (not counted)
    reference_rise = torch.zeros(4, 5)
    reference_rise[0, 3], reference_rise[1, 4], reference_rise[2, 1], reference_rise[3, 2] = 0.10, 0.04, 0.02, 0.02
    object_rise = torch.zeros(4, 5)
    object_rise[0, 2], object_rise[1, 1], object_rise[1, 4] = 0.031, 0.019, 0.021
    object_rise[2, 1], object_rise[3, 2] = 0.05, 0.015
    unstable = torch.zeros(4, 5, dtype=torch.bool)
    unstable[0, 2] = unstable[3, 3] = True
    m = trajectory_metrics(e, valid=valid, lengths=torch.full((4,), 5), palm_limit=0.25,
                           object_rise=object_rise, reference_rise=reference_rise, unstable=unstable)
    assert m["ended_early"].tolist() == [False, True, True, True]
    assert m["ended_palm"].tolist() == [False, True, False, False]
    assert m["ended_unstable"].tolist() == [False, False, False, True]
    assert m["reference_lifts"].tolist() == [True, True, False, False]     # 3 cm or more
    assert m["lifted"].tolist() == [True, False, False, False]              # 3.1 ≥ 3; 1.9 < 2 (2.1 too late)
    s = summarize(m)
    assert s["ended_pct"] == pytest.approx(75.0) and s["ended_palm_pct"] == pytest.approx(25.0)
    assert s["ended_unstable_pct"] == pytest.approx(25.0)
    assert s["lifted_pct"] == pytest.approx(50.0)                           # of the two that the reference lifts
    assert format_summary(s).splitlines()[-1] == ("episodes ended early 75.0 % (the palm beyond its termination "
                                                  "error: 25.0 %, the physics unstable: 25.0 %); objects the "
                                                  "reference lifts, lifted 50.0 %")
    none_lift = summarize(trajectory_metrics(e, object_rise=object_rise, reference_rise=0 * reference_rise))
    assert math.isnan(none_lift["lifted_pct"]) and "ended_palm_pct" not in none_lift
    assert "ended_unstable_pct" not in none_lift
    with pytest.raises(ArrayError, match="object_rise and reference_rise"):
        trajectory_metrics(e, object_rise=object_rise)
    with pytest.raises(ArrayError, match="errors' shape"):
        trajectory_metrics(e, object_rise=object_rise[:, :3], reference_rise=reference_rise[:, :3])

def test_from_rollout_stops_at_first_done():
    B, T = 2, 4
    errs = errors_from({}, B, T)
    errs["T_o"][0, 3] = 5.0          # after the episode's done at frame 2: must not count
    errs["T_o"][1, 1] = 5.0
    done = torch.zeros(B, T, 1, dtype=torch.bool)
    done[0, 2] = True
    td = TensorDict({"next": {"done": done, "privileged": {"errors": TensorDict(
        {k: v[..., None] for k, v in errs.items()}, batch_size=[B, T])}}}, batch_size=[B, T])
    m = from_rollout(td)
    assert m["frames"].tolist() == [3, 4]
    assert m["T_o"][0].item() == 0.0 and m["T_o"][1].item() == pytest.approx(1.25)
    assert m["success_mean_error"].tolist() == [True, False]
    assert m["completion"].tolist() == pytest.approx([1.0, 0.75])


def test_bad_input():
    with pytest.raises(KeyError, match="lack"):
        trajectory_metrics({"T_o": torch.zeros(1, 2)})
    bad = errors_from({}, B=2, T=3)
    bad["R_h"] = torch.zeros(2, 4)
    with pytest.raises(ValueError, match=r"shape \(B, T\)"):
        trajectory_metrics(bad)
    with pytest.raises(ValueError, match="positive"):
        Thresholds(position=-1.0)
    with pytest.raises(ValueError, match="batch shape"):
        from_rollout(TensorDict({}, batch_size=[3]))
    with pytest.raises(ValueError, match="lengths"):
        trajectory_metrics(errors_from({}, 1, 3), lengths=torch.tensor([2]))


def test_paper_defaults():
    th = Thresholds()
    assert th.position == 0.10 and np.degrees(th.rotation) == pytest.approx(60) and np.degrees(th.finger) == pytest.approx(40)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-1, 1, allow_nan=False), min_size=8, max_size=8))
def test_angle_between_equals_angle_of_the_difference(v):
    from adadex.quat import quat_angle_between

    a = torch.tensor(v[:4], dtype=torch.float64)
    b = torch.tensor(v[4:], dtype=torch.float64)
    if a.norm() < 1e-3 or b.norm() < 1e-3:
        return
    a, b = a / a.norm(), b / b.norm()
    assert quat_angle_between(a, b).item() == pytest.approx(quat_angle(quat_diff(a, b)).item(), abs=1e-6)


def test_frame_errors_are_the_envs_own():
    """The env defines the per-frame errors (no upward import); metrics re-exports the same objects."""
    import adadex.envs.frame_errors as env_errors
    import adadex.eval.metrics as metrics

    assert metrics.frame_errors is env_errors.frame_errors and metrics.ERROR_NAMES is env_errors.ERROR_NAMES


def test_from_rollout_takes_any_leading_dims():
    """[workers, B, T] (a multi-process collector's stack) gives the same rows as [workers·B, T]."""
    W, B, T = 2, 3, 4
    errs = errors_from({}, W * B, T)
    errs["T_o"][4, 1:] = 5.0
    done = torch.zeros(W * B, T, 1, dtype=torch.bool)
    flat = TensorDict({"next": {"done": done, "privileged": {"errors": TensorDict(
        {k: v[..., None] for k, v in errs.items()}, batch_size=[W * B, T])}}}, batch_size=[W * B, T])
    stacked = from_rollout(flat.reshape(W, B, T))
    assert stacked["completion"].tolist() == from_rollout(flat)["completion"].tolist()
    assert stacked["completion"][4].item() == pytest.approx(0.25)
    with pytest.raises(ValueError, match="time last"):
        from_rollout(flat[:, 0])
