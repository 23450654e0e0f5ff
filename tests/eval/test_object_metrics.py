"""The object-centric measures beside the paper's: object_success per frame, object completion and
carried per trajectory, on hand-made error arrays; and what from_rollout reads for them."""

import math

import pytest
import torch
from tensordict import TensorDict

from adadex.envs.frame_errors import object_success as env_object_success
from adadex.eval.metrics import (
    ERROR_NAMES,
    Thresholds,
    frame_success,
    from_rollout,
    object_success,
    reference_motion_from_rollout,
    summarize,
    trajectory_metrics,
)


def errors_from(values: dict, B=1, T=1):
    return {k: torch.full((B, T), float(values.get(k, 0.0)), dtype=torch.float64) for k in ERROR_NAMES}


def test_object_success_is_defined_at_the_env_level_and_reexported():
    assert object_success is env_object_success
    th = Thresholds()
    assert (th.object_position, th.carry_motion, th.carry_fraction) == (0.05, 0.03, 0.8)


@pytest.mark.parametrize("values, paper, obj", [
    ({}, True, True),
    ({"T_o": 0.15, "T_h": 0.0}, True, False),     # the paper's test passes with the object 15 cm off
    ({"T_o": 0.19, "T_h": 0.0}, True, False),     # ~19 cm: still the paper's success
    ({"T_o": 0.05, "T_h": 0.0}, True, True),      # on the object threshold
    ({"T_o": 0.051, "T_h": 0.0}, True, False),
    ({"T_o": 0.04, "T_h": 0.17}, False, False),   # object close, palm far: fails the paper's test too
    ({"T_o": 0.0, "E_finger": math.radians(41)}, False, False),
])
def test_object_success_per_frame(values, paper, obj):
    e = errors_from(values)
    assert bool(frame_success(e)[0, 0]) is paper
    assert bool(object_success(e)[0, 0]) is obj


def test_object_success_takes_numpy_and_other_thresholds():
    e = {k: v.numpy() for k, v in errors_from({"T_o": 0.08}).items()}
    assert not object_success(e)[0, 0]
    assert object_success(e, Thresholds(object_position=0.1))[0, 0]
    for bad in ({"object_position": 0.0}, {"carry_motion": -0.01}, {"carry_fraction": 1.5},
                {"carry_fraction": math.nan}):
        with pytest.raises(ValueError, match="Thresholds"):
            Thresholds(**bad)


def test_object_completion_counts_like_completion():
    # 4 frames: the object 15 cm off on frame 2 (paper: pass, object: fail); the trajectory ends
    # after 3 of its 4 frames (the frame never reached fails both).
    e = errors_from({}, B=1, T=4)
    e["T_o"][0, 2] = 0.15
    valid = torch.tensor([[True, True, True, False]])
    m = trajectory_metrics(e, valid=valid, lengths=torch.tensor([4]))
    assert m["completion"].item() == pytest.approx(0.75)
    assert m["object_completion"].item() == pytest.approx(0.5)
    assert m["object_completion"].dtype == torch.float64
    assert "carried" not in m                       # no reference motion given: not measured
    s = summarize(m)
    assert s["object_completion_pct"] == pytest.approx(50.0) and math.isnan(s["carried_pct"])


def _moving(T=10, start=2):
    """Reference object distance from its start: still for ``start`` frames, then 10 cm away."""
    d = torch.zeros(1, T, dtype=torch.float64)
    d[0, start:] = 0.10
    return d


def test_carried_over_the_moving_frames():
    motion = _moving()                          # frames 2..9 move: 8 moving frames
    e = errors_from({}, B=1, T=10)
    e["T_o"][0, :2] = 0.5                       # off while the reference is still: not looked at
    e["T_o"][0, 9] = 0.06                       # 7 of 8 moving frames within 5 cm: 87.5 % ≥ 80 %
    m = trajectory_metrics(e, reference_motion=motion)
    assert m["carried"].tolist() == [True] and m["moving_frames"].tolist() == [8]
    e["T_o"][0, 8] = 0.06                       # 6 of 8: 75 %
    assert trajectory_metrics(e, reference_motion=motion)["carried"].tolist() == [False]
    # the moving threshold: a reference that moves only 3 cm (not more) has no moving frame
    e = errors_from({"T_o": 0.2}, B=1, T=10)
    m = trajectory_metrics(e, reference_motion=torch.full((1, 10), 0.03, dtype=torch.float64))
    assert m["moving_frames"].tolist() == [0]


def test_an_object_left_on_the_table_is_not_carried():
    """The palm follows; the object stays at its start while the reference lifts it 20 cm: the paper's
    completion counts the frames until the object is 20 cm off (mean 10 cm), the object's measures
    tell."""
    T = 20
    motion = torch.linspace(0.0, 0.20, T, dtype=torch.float64)[None]
    e = errors_from({}, B=1, T=T)
    e["T_o"][0] = motion[0]                     # the object error is the reference's motion
    m = trajectory_metrics(e, reference_motion=motion)
    assert m["completion"].item() == pytest.approx(1.0)            # 0.5·T_o ≤ 10 cm throughout
    assert m["object_completion"].item() < 0.3
    assert m["carried"].tolist() == [False]


def test_a_still_reference_is_carried_by_its_object_completion():
    still = torch.zeros(2, 10, dtype=torch.float64)
    e = errors_from({}, B=2, T=10)
    e["T_o"][0, :2] = 0.2                       # object completion 0.8: carried
    e["T_o"][1, :3] = 0.2                       # 0.7: not
    m = trajectory_metrics(e, reference_motion=still)
    assert m["object_completion"].tolist() == pytest.approx([0.8, 0.7])
    assert m["carried"].tolist() == [True, False] and m["moving_frames"].tolist() == [0, 0]


def test_frames_never_reached_fail_the_carry_and_empty_is_not_carried():
    motion = _moving(T=10, start=0).expand(2, 10)
    e = errors_from({}, B=2, T=10)
    valid = torch.ones(2, 10, dtype=torch.bool)
    valid[0, 7:] = False                        # ended early: 7 of 10 moving frames reached
    valid[1] = False                            # empty
    m = trajectory_metrics(e, valid=valid, lengths=torch.tensor([10, 10]), reference_motion=motion)
    assert m["carried"].tolist() == [False, False]
    s = summarize(m)
    assert s["trajectories"] == 1 and s["carried_pct"] == 0.0 and s["object_completion_pct"] == pytest.approx(70.0)
    with pytest.raises(ValueError, match="reference_motion"):
        trajectory_metrics(e, reference_motion=torch.zeros(2, 9))


def _rollout(T=6, modulated=False):
    B = 2
    errs = errors_from({}, B, T)
    errs["T_o"][1] = 0.12                       # row 1: object 12 cm off throughout
    ref = torch.zeros(B, T, 5, 7)
    ref[..., 3] = 1.0
    ref[:, :, 0, 2] = torch.linspace(0.01, 0.2, T)          # the reference lifts the object
    start = torch.zeros(B, T, 7)
    start[..., 3] = 1.0
    td = TensorDict({"next": {"done": torch.zeros(B, T, 1, dtype=torch.bool),
                              "privileged": {"errors": TensorDict({k: v[..., None].float() for k, v in errs.items()},
                                                                  batch_size=[B, T])},
                              "reference": {"object_pose": ref}, "object": {"reference_start": start}}},
                    batch_size=[B, T])
    if modulated:
        td["modulation", "action"] = torch.zeros(B, T, 3)
    return td


def test_from_rollout_reads_the_reference_motion_the_env_writes():
    td = _rollout()
    motion = reference_motion_from_rollout(td)
    assert motion.shape == (2, 6) and motion[0, -1].item() == pytest.approx(0.2)
    m = from_rollout(td)
    assert m["carried"].tolist() == [True, False]
    assert m["completion"].tolist() == [1.0, 1.0] and m["object_completion"].tolist() == [1.0, 0.0]
    # a modulated rollout shows the edited reference: not read, carried needs the motion given
    assert reference_motion_from_rollout(_rollout(modulated=True)) is None
    assert "carried" not in from_rollout(_rollout(modulated=True))
    given = from_rollout(_rollout(modulated=True), reference_motion=motion)
    assert given["carried"].tolist() == [True, False]
