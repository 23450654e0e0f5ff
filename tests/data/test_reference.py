"""Tests of hand–object references: validation messages, episode windows, and on-disk datasets."""

import json
import os
import re
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import adadex.io
import adadex.data.reference as reference_module
from adadex.data.reference import (
    FORMAT_VERSION,
    JOINT_LIMIT_TOLERANCE,
    NUM_KEYPOINTS,
    QUAT_NORM_TOLERANCE,
    WINDOW_FRAMES,
    WINDOW_START_DISTANCE,
    DatasetError,
    JointLimitError,
    QuaternionNormError,
    Reference,
    ReferenceDataset,
    ReferenceError,
    ReferenceObjectError,
    ReferenceShapeError,
    ReferenceValueError,
    WindowTooShortError,
    check_splits,
    save_dataset,
)
from adadex.sim.kinematics import RobotKinematics
from adadex.sim.objects import UnknownObjectError, get_object
from adadex.sim.robot import HOME_QPOS, JOINT_NAMES, NUM_JOINTS, TRACKED_SITES, joint_limits
from adadex.sim.scene import CONTROL_HZ

HALF_HEIGHT = get_object("cube_050").half_height
#: cube_050 resting on the table in front of the robot.
REST = np.array([0.45, 0.0, HALF_HEIGHT, 1.0, 0.0, 0.0, 0.0])
#: An arm pose that puts the palm a few cm from the cube centre (at HOME_QPOS it is ~0.33 m away).
NEAR_QPOS = HOME_QPOS.copy()
NEAR_QPOS[[1, 2, 4]] = [0.55, -1.0056, 0.8]
HOLD, MOVE = 3, 10      # frames at NEAR_QPOS, then frames of a smooth move to HOME_QPOS
FRAME_FIELDS = ("hand_joint_pos", "hand_link_pose", "object_pose", "human_keypoints", "retarget_residual")


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Forward kinematics of a few hundred frames gains nothing from threads, and on a busy machine a second
    intra-op thread makes it ~50× slower; restore the session's setting afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@lru_cache(maxsize=1)
def fk() -> RobotKinematics:
    return RobotKinematics()


def joint_traj(T=320, seed=0, wiggle=0.08):
    """Palm near the cube for HOLD frames, moving away over MOVE frames, fingers wiggling throughout."""
    s = np.clip((np.arange(T) - HOLD) / MOVE, 0.0, 1.0)
    s = s * s * (3 - 2 * s)
    q = NEAR_QPOS + s[:, None] * (HOME_QPOS - NEAR_QPOS)
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, NUM_JOINTS - 6)
    q[:, 6:] += wiggle * np.sin(2 * np.pi * np.arange(T)[:, None] / 60.0 + phase)
    return q


MAX_T = 330


@lru_cache(maxsize=None)
def _full_ref(seed) -> Reference:
    """A MAX_T-frame reference; shorter ones are its prefixes (joint_traj(T) is a prefix of joint_traj(MAX_T))."""
    rng = np.random.default_rng(1000 + seed)
    return Reference.from_joint_positions(
        joint_traj(MAX_T, seed), np.tile(REST, (MAX_T, 1)), object_name="cube_050",
        instruction=f"pick up the cube #{seed}", group_id=seed // 2,
        meta={"verb": "pick", "seed": seed, "params": [0.1, seed]},
        human_keypoints=rng.uniform(-1, 1, (MAX_T, NUM_KEYPOINTS, 3)), retarget_residual=rng.uniform(0, 0.05, MAX_T))


def make_ref(T=320, seed=0, keypoints=False, residual=False, name=""):
    full = _full_ref(seed)
    f = {k: getattr(full, k) for k in ("object_name", "instruction", "group_id", "fps", "meta")}
    for k in FRAME_FIELDS:
        f[k] = getattr(full, k)[:T]
    f["human_keypoints"] = f["human_keypoints"] if keypoints else None
    f["retarget_residual"] = f["retarget_residual"] if residual else None
    return Reference(**f, name=name)


def fields(ref: Reference) -> dict:
    """Constructor arguments of ``ref`` as writable copies, to corrupt one at a time."""
    out = {k: getattr(ref, k) for k in ("object_name", "instruction", "group_id", "fps", "meta", "name")}
    for k in FRAME_FIELDS:
        v = getattr(ref, k)
        out[k] = None if v is None else v.copy()
    return out


def palm_distance(q, obj):
    palm = fk().link_poses(torch.tensor(q)).numpy()[:, 0, :3]
    return np.linalg.norm(palm - obj[:, :3], axis=-1)


def assert_refs_close(a: Reference, b: Reference, atol=1e-6):
    for k in FRAME_FIELDS:
        va, vb = getattr(a, k), getattr(b, k)
        assert (va is None) == (vb is None), k
        if va is not None:
            assert va.shape == vb.shape, k
            np.testing.assert_allclose(va, vb, rtol=0, atol=atol, err_msg=k)
    for k in ("object_name", "instruction", "group_id", "fps", "meta"):
        assert getattr(a, k) == getattr(b, k), k
    np.testing.assert_allclose(np.linalg.norm(b.hand_link_pose[..., 3:], axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(b.object_pose[:, 3:], axis=-1), 1.0, atol=1e-12)


def leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


# ---------------------------------------------------------------------------- a valid reference


def test_valid_reference_shapes_fields_and_read_only_copies():
    q = joint_traj(320)
    obj = np.tile(REST, (320, 1))
    ref = Reference.from_joint_positions(q, obj, object_name="cube_050", instruction="lift it", group_id=np.int64(4))
    assert ref.hand_joint_pos.shape == (320, NUM_JOINTS)
    assert ref.hand_link_pose.shape == (320, len(TRACKED_SITES), 7)
    assert ref.object_pose.shape == (320, 7)
    assert ref.human_keypoints is None and ref.retarget_residual is None
    assert ref.fps == CONTROL_HZ and ref.num_frames == 320 and ref.duration == pytest.approx(320 / CONTROL_HZ)
    assert ref.group_id == 4 and type(ref.group_id) is int
    assert ref.meta == {} and ref.name == ""
    for k in ("hand_joint_pos", "hand_link_pose", "object_pose"):
        arr = getattr(ref, k)
        assert arr.dtype == np.float64
        with pytest.raises(ValueError, match="read-only"):
            arr[0, 0] = 1.0
    np.testing.assert_array_equal(ref.hand_joint_pos, q)
    q[:] = 0.0                                      # the reference holds a copy
    assert ref.hand_joint_pos[0, 1] == NEAR_QPOS[1]
    with pytest.raises(AttributeError):
        ref.instruction = "other"
    named = ref.with_name("r1")
    assert named.name == "r1" and ref.name == ""
    np.testing.assert_array_equal(named.hand_link_pose, ref.hand_link_pose)


def test_from_joint_positions_link_poses_are_the_forward_kinematics():
    q = joint_traj(310, seed=3)
    ref = Reference.from_joint_positions(q, np.tile(REST, (310, 1)), object_name="cube_050",
                                         instruction="", group_id=0)
    expected = fk().link_poses(torch.as_tensor(q)).numpy()
    np.testing.assert_allclose(ref.hand_link_pose, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(ref.hand_link_pose[..., 3:], axis=-1), 1.0, atol=1e-9)
    # Keyword arguments pass through to the constructor.
    kp = np.zeros((310, NUM_KEYPOINTS, 3))
    ref = Reference.from_joint_positions(q, np.tile(REST, (310, 1)), object_name="cube_050", instruction="x",
                                         group_id=1, fps=30.0, human_keypoints=kp, name="n", meta={"a": 1})
    assert (ref.fps, ref.name, ref.meta, ref.human_keypoints.shape) == (30.0, "n", {"a": 1}, (310, 21, 3))


def test_test_references_are_from_joint_positions_prefixes():
    ref = make_ref(305, seed=2, keypoints=True)
    direct = Reference.from_joint_positions(joint_traj(305, seed=2), np.tile(REST, (305, 1)),
                                            object_name="cube_050", instruction="", group_id=0)
    for k in ("hand_joint_pos", "hand_link_pose", "object_pose"):
        np.testing.assert_allclose(getattr(ref, k), getattr(direct, k), rtol=0, atol=1e-12)


def test_home_palm_is_far_from_the_resting_cube_and_near_pose_is_close():
    # Guards the test data itself: the window start below relies on it.
    d = palm_distance(np.stack([HOME_QPOS, NEAR_QPOS]), np.tile(REST, (2, 1)))
    assert d[0] > WINDOW_START_DISTANCE + 0.05 and d[1] < 0.1


def test_window_starts_at_the_first_frame_with_the_palm_far_from_the_object():
    ref = make_ref(320)
    d = palm_distance(ref.hand_joint_pos, ref.object_pose)
    np.testing.assert_allclose(ref.palm_object_distance(), d, atol=1e-12)
    start = ref.window_start()
    assert HOLD < start < HOLD + MOVE
    assert d[start] > WINDOW_START_DISTANCE and (d[:start] <= WINDOW_START_DISTANCE).all()
    assert start == int(np.flatnonzero(d > WINDOW_START_DISTANCE)[0])
    w = ref.window()
    assert w == slice(start, start + WINDOW_FRAMES) and len(range(320)[w]) == WINDOW_FRAMES == 300
    assert ref.validate() is ref
    # Other thresholds and lengths.
    assert ref.window_start(distance=0.0) == 0
    assert ref.window_start(distance=0.3) > start
    assert ref.window(frames=10) == slice(start, start + 10)


def test_window_exactly_fits():
    start = make_ref(320).window_start()
    ref = make_ref(start + WINDOW_FRAMES)
    assert ref.window() == slice(start, ref.num_frames)


@pytest.mark.parametrize("missing", [1, 7])
def test_window_too_short_says_how_many_frames_are_missing(missing):
    start = make_ref(320).window_start()
    ref = make_ref(start + WINDOW_FRAMES - missing).with_name("short")
    with pytest.raises(WindowTooShortError,
                       match=rf"^reference 'short': {ref.num_frames} frames, the episode starts at frame {start} "
                             rf"and needs 300 frames, so {missing} are missing$"):
        ref.window()
    with pytest.raises(WindowTooShortError, match=f"so {missing} are missing"):
        ref.validate()
    ref.validate(frames=WINDOW_FRAMES - missing)     # a shorter episode fits


def test_window_when_the_palm_never_leaves_the_object():
    q = np.tile(HOME_QPOS, (310, 1))
    palm = fk().link_poses(torch.as_tensor(q[:1])).numpy()[0, 0, :3]
    obj = np.tile(np.r_[palm + [0.0, 0.0, -0.1], 1, 0, 0, 0], (310, 1))   # cube held 10 cm under the palm
    ref = Reference.from_joint_positions(q, obj, object_name="cube_050", instruction="", group_id=0, name="stuck")
    with pytest.raises(WindowTooShortError, match=r"reference 'stuck': the palm never gets farther than 0\.2 m"):
        ref.window_start()
    with pytest.raises(ReferenceError):
        ref.validate()


# ---------------------------------------------------------------------------- validation messages


def all_fields():
    return fields(make_ref(320, keypoints=True, residual=True, name="r7"))


@pytest.mark.parametrize("field, index", [
    ("hand_joint_pos", (17, 8)),
    ("hand_link_pose", (17, 2, 1)),
    ("hand_link_pose", (17, 0, 4)),            # in a quaternion: reported as non-finite, not as a norm
    ("object_pose", (17, 2)),
    ("object_pose", (17, 5)),
    ("human_keypoints", (17, 20, 2)),
    ("retarget_residual", (17,)),
])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values_name_field_and_frame(field, index, bad):
    f = all_fields()
    f[field][index] = bad
    later = list(index)
    later[0] = 200
    f[field][tuple(later)] = bad                    # the first bad frame is reported
    idx = re.escape(str(tuple(index)))
    with pytest.raises(ReferenceValueError,
                       match=rf"^reference 'r7': {field}: non-finite value -?(nan|inf) at frame 17 \(index {idx}\)"):
        Reference(**f)


@pytest.mark.parametrize("field, shape, pattern", [
    ("hand_joint_pos", (320, 21), r"hand_joint_pos: expected shape \(T, 22\), got \(320, 21\)"),
    ("hand_joint_pos", (320,), r"hand_joint_pos: expected shape \(T, 22\), got \(320,\)"),
    ("hand_joint_pos", (1, 320, 22), r"hand_joint_pos: expected shape \(T, 22\), got \(1, 320, 22\)"),
    ("hand_link_pose", (320, 4, 7), r"hand_link_pose: expected shape \(T, 5, 7\), got \(320, 4, 7\)"),
    ("hand_link_pose", (320, 5, 3), r"hand_link_pose: expected shape \(T, 5, 7\), got \(320, 5, 3\)"),
    ("object_pose", (320, 3), r"object_pose: expected shape \(T, 7\), got \(320, 3\)"),
    ("object_pose", (7,), r"object_pose: expected shape \(T, 7\), got \(7,\)"),
    ("human_keypoints", (320, 20, 3), r"human_keypoints: expected shape \(T, 21, 3\), got \(320, 20, 3\)"),
    ("retarget_residual", (320, 1), r"retarget_residual: expected shape \(T,\), got \(320, 1\)"),
])
def test_wrong_shapes_say_expected_and_got(field, shape, pattern):
    f = all_fields()
    f[field] = np.ones(shape)
    with pytest.raises(ReferenceShapeError, match="^reference 'r7': " + pattern):
        Reference(**f)


@pytest.mark.parametrize("field", ["hand_link_pose", "object_pose", "human_keypoints", "retarget_residual"])
@pytest.mark.parametrize("frames", [319, 321])
def test_frame_count_mismatch_names_both_fields(field, frames):
    f = all_fields()
    f[field] = np.resize(f[field], (frames, *f[field].shape[1:]))
    with pytest.raises(ReferenceShapeError, match=rf"^reference 'r7': {field} has {frames} frames, "
                                                  r"hand_joint_pos has 320$"):
        Reference(**f)


def test_from_joint_positions_reports_joint_shape_errors():
    with pytest.raises(ReferenceShapeError,
                       match=r"^reference: hand_joint_pos: expected shape \(T, 22\), got \(320, 7\)"):
        Reference.from_joint_positions(np.zeros((320, 7)), np.tile(REST, (320, 1)), object_name="cube_050",
                                       instruction="", group_id=0)
    with pytest.raises(ReferenceShapeError, match=r"hand_joint_pos: expected shape \(T, 22\), got \(22,\)"):
        Reference.from_joint_positions(HOME_QPOS, REST, object_name="cube_050", instruction="", group_id=0)


def test_unconvertible_array_is_a_reference_error():
    f = all_fields()
    f["object_pose"] = [[0.0] * 7, [0.0] * 6]
    with pytest.raises(ReferenceError, match=r"^reference 'r7': object_pose: cannot convert to a float array"):
        Reference(**f)
    f = all_fields()
    f["retarget_residual"] = ["abc"] * 320
    with pytest.raises(ReferenceError, match=r"retarget_residual: cannot convert"):
        Reference(**f)


@pytest.mark.parametrize("scale", [1 + 2 * QUAT_NORM_TOLERANCE, 1 - 2 * QUAT_NORM_TOLERANCE, 0.0, 2.0])
def test_non_unit_link_quaternion_names_frame_and_link(scale):
    f = all_fields()
    f["hand_link_pose"][41, 3, 3:] *= scale
    with pytest.raises(QuaternionNormError,
                       match=rf"^reference 'r7': hand_link_pose: quaternion at frame 41 \(index \(41, 3\)\) "
                             rf"has norm {abs(scale):.6f}, expected 1 ± 0\.001$"):
        Reference(**f)


@pytest.mark.parametrize("scale", [1 + 2 * QUAT_NORM_TOLERANCE, 0.5, 0.0])
def test_non_unit_object_quaternion_names_frame(scale):
    f = all_fields()
    f["object_pose"][250, 3:] *= scale
    with pytest.raises(QuaternionNormError,
                       match=rf"^reference 'r7': object_pose: quaternion at frame 250 \(index \(250,\)\) "
                             rf"has norm {scale:.6f}"):
        Reference(**f)


def test_quaternion_norm_within_tolerance_is_accepted():
    f = all_fields()
    f["hand_link_pose"][5, 1, 3:] *= 1 + 0.5 * QUAT_NORM_TOLERANCE
    f["object_pose"][6, 3:] *= 1 - 0.5 * QUAT_NORM_TOLERANCE
    Reference(**f)


@pytest.mark.parametrize("joint, side, excess, frame", [
    ("if_pip", 1, 0.03, 42), ("th_ipl", 0, 0.5, 0), ("arm_j3", 1, 0.021, 319),
])
def test_joint_outside_limits_names_joint_and_frame(joint, side, excess, frame):
    j = JOINT_NAMES.index(joint)
    lim = joint_limits()[j]
    q = joint_traj(320)
    q[frame, j] = lim[side] + (excess if side else -excess)
    with pytest.raises(JointLimitError,
                       match=rf"^reference 'j': joint {joint} at frame {frame} is [+-]\d\.\d{{4}} rad, outside "
                             + re.escape(f"[{lim[0]:+.4f}, {lim[1]:+.4f}] by {excess:.4f} (tolerance 0.02)") + "$"):
        Reference.from_joint_positions(q, np.tile(REST, (320, 1)), object_name="cube_050", instruction="",
                                       group_id=0, name="j")


def test_joint_limit_error_reports_the_worst_violation():
    q = joint_traj(320)
    lim = joint_limits()
    q[10, 8] = lim[8, 1] + 0.03
    q[20, 12] = lim[12, 0] - 0.2
    with pytest.raises(JointLimitError, match=r"joint mf_pip at frame 20 .* by 0\.2000"):
        Reference.from_joint_positions(q, np.tile(REST, (320, 1)), object_name="cube_050", instruction="",
                                       group_id=0)


def test_joints_slightly_outside_limits_within_tolerance_are_accepted():
    q = joint_traj(320)
    lim = joint_limits()
    q[0] = lim[:, 1] + 0.9 * JOINT_LIMIT_TOLERANCE
    q[1] = lim[:, 0] - 0.9 * JOINT_LIMIT_TOLERANCE
    ref = Reference.from_joint_positions(q, np.tile(REST, (320, 1)), object_name="cube_050", instruction="",
                                         group_id=0)
    np.testing.assert_array_equal(ref.hand_joint_pos[:2], q[:2])


def test_unknown_object_is_also_an_objects_unknown_object_error():
    f = all_fields()
    f["object_name"] = "cube_051"
    with pytest.raises(ReferenceObjectError, match=r"^reference 'r7': unknown object 'cube_051' \(see `adadex sim info`"
                                                   r" for the \d+ known objects\)$"):
        Reference(**f)
    for cls in (UnknownObjectError, KeyError, ReferenceError, ValueError):
        with pytest.raises(cls):
            Reference(**f)
    try:
        Reference(**f)
    except KeyError as e:                           # str() is the message, not its repr as KeyError's would be
        assert str(e).startswith("reference 'r7': unknown object")


@pytest.mark.parametrize("fps", [0, -12.0, np.nan, np.inf, -np.inf, "fast", None])
def test_bad_fps(fps):
    f = all_fields()
    f["fps"] = fps
    with pytest.raises(ReferenceError, match=r"^reference 'r7': fps must be a positive number, got"):
        Reference(**f)


def test_every_error_class_is_a_reference_error_and_a_value_error():
    for cls in (ReferenceShapeError, ReferenceValueError, QuaternionNormError, JointLimitError,
                ReferenceObjectError, WindowTooShortError, DatasetError):
        assert issubclass(cls, ReferenceError) and issubclass(cls, ValueError), cls


def test_unnamed_reference_messages_say_reference():
    f = all_fields()
    f["name"] = ""
    f["object_pose"][3, 0] = np.nan
    with pytest.raises(ReferenceValueError, match=r"^reference: object_pose: non-finite value nan at frame 3 "):
        Reference(**f)


# ---------------------------------------------------------------------------- datasets: round trip


def some_refs():
    return [
        make_ref(320, seed=0, keypoints=True, residual=True, name="a"),
        make_ref(300, seed=1),
        make_ref(330, seed=2, residual=True, name="c"),
        make_ref(315, seed=3, keypoints=True),
    ]


def test_save_load_round_trip(tmp_path):
    refs = some_refs()
    splits = {"unseen_trajectory": {"train": [0, 1, 3], "test": [2]},
              "unseen_object": {"train": np.array([3, 2]), "test": [np.int64(0)]}}
    info = {"seed": np.int64(7), "rejected": {"too_short": 2}, "scale": np.float32(0.5)}
    out = save_dataset(refs, tmp_path / "ds", splits=splits, info=info)
    assert out == tmp_path / "ds"
    assert sorted(os.listdir(out)) == ["frames", "index.json", "splits.json"]
    assert os.listdir(tmp_path) == ["ds"]

    ds = ReferenceDataset(out)
    assert len(ds) == 4 and ds.num_frames == sum(r.num_frames for r in refs) == 1265
    assert ds.info == {"seed": 7, "rejected": {"too_short": 2}, "scale": 0.5}
    assert ds.splits == {"unseen_trajectory": {"train": [0, 1, 3], "test": [2]},
                         "unseen_object": {"train": [3, 2], "test": [0]}}
    assert [e["name"] for e in ds.entries] == ["a", "ref00001", "c", "ref00003"]
    assert [e["offset"] for e in ds.entries] == [0, 320, 620, 950]
    assert [e["window_start"] for e in ds.entries] == [r.window_start() for r in refs]
    assert "4 references, 1265 frames" in repr(ds)
    for r, back in zip(refs, ds):
        assert_refs_close(r, back)
        assert back.hand_joint_pos.dtype == np.float64
        assert back.name == (r.name or back.name) and back.name
    assert ds[0].human_keypoints is not None and ds[0].retarget_residual is not None
    assert ds[1].human_keypoints is None and ds[1].retarget_residual is None
    assert ds[2].human_keypoints is None and ds[2].retarget_residual is not None
    assert ds[3].human_keypoints is not None and ds[3].retarget_residual is None
    assert ds[0].meta == {"verb": "pick", "seed": 0, "params": [0.1, 0]}
    # The concatenated frames are float32 and addressed by offset + t.
    fr = ds.frames
    assert fr.batch_size[0] == 1265 and fr["hand_link_pose"].dtype == torch.float32
    e = ds.entries[2]
    np.testing.assert_allclose(fr["hand_joint_pos"][e["offset"] + 17].numpy(), refs[2].hand_joint_pos[17], atol=1e-6)
    # The index records what the module docstring promises.
    index = json.loads((out / "index.json").read_text())
    assert index["version"] == FORMAT_VERSION and index["num_references"] == 4
    assert index["num_frames"] == 1265 and index["window_frames"] == WINDOW_FRAMES


def test_window_start_of_a_reference_that_never_starts_is_stored_as_none(tmp_path):
    q = np.tile(HOME_QPOS, (300, 1))
    palm = fk().link_poses(torch.as_tensor(q[:1])).numpy()[0, 0, :3]
    obj = np.tile(np.r_[palm - [0, 0, 0.1], 1, 0, 0, 0], (300, 1))
    ref = Reference.from_joint_positions(q, obj, object_name="cube_050", instruction="", group_id=0)
    ds = ReferenceDataset(save_dataset([ref], tmp_path / "ds"))
    assert ds.entries[0]["window_start"] is None
    assert_refs_close(ref, ds[0])


def test_opening_is_lazy(tmp_path):
    out = save_dataset(some_refs()[:2], tmp_path / "ds", splits={"s": {"train": [0], "test": [1]}})
    ds = ReferenceDataset(out)
    assert ds._frames is None
    assert len(ds) == 2 and ds.entries[1]["length"] == 300 and ds.split("s", "test") == [1]
    list(ds.entries)
    repr(ds)
    assert ds._frames is None
    ds[1]
    assert ds._frames is not None
    # Opening never looks at frames/ at all.
    (out / "frames").rename(tmp_path / "elsewhere")
    ds = ReferenceDataset(out)
    assert len(ds) == 2 and ds._frames is None


def test_indexing_negative_slices_and_out_of_range(tmp_path):
    refs = some_refs()
    ds = ReferenceDataset(save_dataset(refs, tmp_path / "ds"))
    assert ds[-1].name == "ref00003" and ds[-4].name == "a"
    assert_refs_close(refs[-2], ds[-2])
    assert [r.name for r in ds[1:3]] == ["ref00001", "c"]
    assert [r.name for r in ds[::-2]] == ["ref00003", "ref00001"]
    assert [r.name for r in ds[-2:]] == ["c", "ref00003"]
    assert ds[10:] == []
    for i in (4, -5, 100):
        with pytest.raises(IndexError, match=rf"reference index {i} out of range for a dataset of 4"):
            ds[i]
    assert [r.name for r in ds] == ["a", "ref00001", "c", "ref00003"]


def test_frames_count_mismatch_is_reported_every_time(tmp_path):
    out = save_dataset(some_refs()[:1], tmp_path / "ds")
    index = json.loads((out / "index.json").read_text())
    index["num_frames"] += 5
    (out / "index.json").write_text(json.dumps(index))
    ds = ReferenceDataset(out)
    for _ in range(2):
        with pytest.raises(DatasetError, match=rf"{re.escape(str(out))}: index.json counts 325 frames, "
                                               r"frames/ holds 320"):
            ds.frames


# ---------------------------------------------------------------------------- datasets: splits


def test_splits_round_trip_and_split_lookup(tmp_path):
    splits = {"unseen_trajectory": {"train": [0, 1], "test": [2, 3]}, "unseen_object": {"train": [1, 2, 3]}}
    ds = ReferenceDataset(save_dataset(some_refs(), tmp_path / "ds", splits=splits))
    assert ds.splits == splits
    assert ds.split("unseen_trajectory", "test") == [2, 3]
    got = ds.split("unseen_object", "train")
    got.append(0)                                   # a copy
    assert ds.split("unseen_object", "train") == [1, 2, 3]
    with pytest.raises(KeyError, match=r"no split 'unseen_objects'; available: \['unseen_object', "
                                       r"'unseen_trajectory'\]"):
        ds.split("unseen_objects", "train")
    with pytest.raises(KeyError, match=r"split 'unseen_object' has no part 'test'; available: \['train'\]"):
        ds.split("unseen_object", "test")
    ds = ReferenceDataset(save_dataset(some_refs(), tmp_path / "nosplits"))
    assert ds.splits == {}
    with pytest.raises(KeyError, match=r"no split 'unseen_object'; available: \[\]"):
        ds.split("unseen_object", "train")


@pytest.mark.parametrize("splits, pattern", [
    ({"s": {"train": [0, 4]}}, r"^split 's'/train: index 4 outside 0\.\.3$"),
    ({"s": {"train": [-1]}}, r"^split 's'/train: index -1 outside 0\.\.3$"),
    ({"s": {"train": [0, 1], "test": [1, 2]}}, r"^split 's': reference 1 is in both 'train' and 'test'$"),
    ({"s": {"train": [0, 0]}}, r"^split 's'/train: reference 0 appears twice"),
    ({"s": [0, 1]}, r"^split 's': expected \{part: \[indices\]\}, got list$"),
    ({"s": {"train": [0.5]}}, r"^split 's'/train: index 0\.5 is not an integer"),
    ({"s": {"train": ["x"]}}, r"^split 's'/train: index 'x' is not an integer"),
    ({"s": {"train": 3}}, r"^split 's'/train: expected a list of indices, got int"),
    ({"s": {"train": "01"}}, r"^split 's'/train: expected a list of indices, got str"),
    ({"s": {"train": np.array(2)}}, r"^split 's'/train: expected a list of indices, got ndarray"),
    ([{"train": [0]}], r"^splits: expected \{name: \{part: \[indices\]\}\}, got list$"),
])
def test_check_splits_errors(splits, pattern):
    with pytest.raises(DatasetError, match=pattern):
        check_splits(splits, 4)


def test_check_splits_allows_the_same_reference_in_different_splits():
    splits = {"a": {"train": [0, 1], "test": [2]}, "b": {"train": (2, np.int64(1)), "test": np.array([0])}}
    out = check_splits(splits, 3)
    assert out == {"a": {"train": [0, 1], "test": [2]}, "b": {"train": [2, 1], "test": [0]}}
    assert all(type(i) is int for part in out["b"].values() for i in part)


@pytest.mark.parametrize("splits", [{"s": {"train": [0, 9]}}, {"s": {"train": [0], "test": [0]}}])
def test_bad_splits_write_nothing(tmp_path, splits):
    with pytest.raises(DatasetError):
        save_dataset(some_refs(), tmp_path / "ds", splits=splits)
    assert os.listdir(tmp_path) == []
    # Nor do they touch an existing dataset.
    save_dataset(some_refs()[:1], tmp_path / "ds")
    with pytest.raises(DatasetError):
        save_dataset(some_refs(), tmp_path / "ds", splits=splits)
    assert len(ReferenceDataset(tmp_path / "ds")) == 1 and os.listdir(tmp_path) == ["ds"]


# ---------------------------------------------------------------------------- datasets: refusals, atomicity


def test_empty_dataset_is_refused(tmp_path):
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(tmp_path / 'ds'))}: refusing to write an empty dataset"):
        save_dataset([], tmp_path / "ds")
    assert os.listdir(tmp_path) == []


def test_duplicate_names_are_refused(tmp_path):
    refs = [make_ref(300, 0, name="x"), make_ref(300, 1, name="y"), make_ref(300, 2, name="x")]
    with pytest.raises(DatasetError, match=r"duplicate reference names \['x'\]"):
        save_dataset(refs, tmp_path / "ds")
    # A given name may not collide with the default name of an unnamed reference either.
    with pytest.raises(DatasetError, match=r"duplicate reference names \['ref00000'\]"):
        save_dataset([make_ref(300, 0), make_ref(300, 1, name="ref00000")], tmp_path / "ds")
    assert os.listdir(tmp_path) == []


def test_overwrite_false_refuses_an_existing_folder(tmp_path):
    out = save_dataset(some_refs()[:1], tmp_path / "ds", overwrite=False)   # fine when absent
    with pytest.raises(FileExistsError, match="overwrite=True"):
        save_dataset(some_refs()[1:2], out, overwrite=False)
    assert ReferenceDataset(out)[0].name == "a"
    (tmp_path / "other").mkdir()
    with pytest.raises(FileExistsError):
        save_dataset(some_refs()[1:2], tmp_path / "other", overwrite=False)


def test_overwrite_replaces_and_leaves_no_temporaries(tmp_path):
    out = save_dataset(some_refs(), tmp_path / "ds", splits={"s": {"train": [3]}}, info={"v": 1})
    save_dataset(some_refs()[1:2], out, info={"v": 2})
    ds = ReferenceDataset(out)
    assert len(ds) == 1 and ds.info == {"v": 2} and ds.splits == {} and ds.num_frames == 300
    assert_refs_close(some_refs()[1], ds[0])
    assert os.listdir(tmp_path) == ["ds"]


def _assert_old_dataset_intact(tmp_path, out):
    ds = ReferenceDataset(out)
    assert len(ds) == 4 and ds.info == {"v": "old"}
    for r, back in zip(some_refs(), ds):
        assert_refs_close(r, back)
    assert os.listdir(tmp_path) == ["ds"], leftovers(tmp_path)


def test_failed_overwrite_keeps_the_old_dataset(tmp_path, monkeypatch):
    out = save_dataset(some_refs(), tmp_path / "ds", info={"v": "old"})

    def broken(refs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(reference_module, "_frames_tensordict", broken)
    with pytest.raises(RuntimeError, match="disk on fire"):
        save_dataset(some_refs()[:1], out, info={"v": "new"})
    _assert_old_dataset_intact(tmp_path, out)


def test_failure_after_frames_were_written_keeps_the_old_dataset(tmp_path, monkeypatch):
    out = save_dataset(some_refs(), tmp_path / "ds", info={"v": "old"})
    real = reference_module.atomic_write_text

    def fail_on_index(path, text):
        if Path(path).name == "index.json":
            raise OSError("no space left")
        return real(path, text)

    monkeypatch.setattr(reference_module, "atomic_write_text", fail_on_index)
    with pytest.raises(OSError, match="no space left"):
        save_dataset(some_refs()[:1], out, info={"v": "new"})
    _assert_old_dataset_intact(tmp_path, out)
    # A meta that is not JSON-serializable fails the same way.
    monkeypatch.undo()
    bad = fields(make_ref(300, 1))
    bad["meta"] = {"x": object()}
    with pytest.raises(TypeError, match="not JSON-serializable"):
        save_dataset([Reference(**bad)], out)
    _assert_old_dataset_intact(tmp_path, out)


def test_failed_final_rename_restores_the_old_dataset(tmp_path, monkeypatch):
    out = save_dataset(some_refs(), tmp_path / "ds", info={"v": "old"})
    real = os.replace

    def replace(src, dst):
        if Path(dst) == out and Path(src).name.endswith(".tmp"):
            raise OSError("rename failed")
        return real(src, dst)

    monkeypatch.setattr(adadex.io.os, "replace", replace)   # the folder swap moved to adadex.io
    with pytest.raises(OSError, match="rename failed"):
        save_dataset(some_refs()[:1], out, info={"v": "new"})
    monkeypatch.undo()
    _assert_old_dataset_intact(tmp_path, out)


def test_save_creates_parent_folders(tmp_path):
    out = save_dataset(some_refs()[:1], str(tmp_path / "a" / "b" / "ds"))
    assert isinstance(out, Path) and len(ReferenceDataset(out)) == 1


# ---------------------------------------------------------------------------- datasets: unreadable folders


def test_folder_without_index_json(tmp_path):
    (tmp_path / "empty").mkdir()
    for folder in (tmp_path / "empty", tmp_path / "absent"):
        with pytest.raises(DatasetError,
                           match=rf"^{re.escape(str(folder))}: not a reference dataset \(no index\.json\)"):
            ReferenceDataset(folder)


@pytest.mark.parametrize("content", [
    b"",
    b'{"version": 1, "num_refer',
    b"\xff\xfe\x00 binary garbage",
    b"[1, 2, 3]",
    b'"a string"',
    b'{"version": 1}',
    b'{"version": 1, "num_references": 1}',
    b'{"version": 1, "num_references": 1, "num_frames": 320}',
    b'{"version": 1, "num_references": 1, "references": []}',
])
def test_corrupted_index_json_names_the_folder(tmp_path, content):
    out = save_dataset(some_refs()[:1], tmp_path / "ds")
    (out / "index.json").write_bytes(content)
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(out))}: "):
        ReferenceDataset(out)


@pytest.mark.parametrize("content", [b"{not json", b'{"s": {"train": [5]}}', b"[1]", b'{"s": [0]}'])
def test_corrupted_splits_json_names_the_folder(tmp_path, content):
    out = save_dataset(some_refs()[:1], tmp_path / "ds")
    (out / "splits.json").write_bytes(content)
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(out))}: "):
        ReferenceDataset(out)


def test_missing_splits_json_and_wrong_version(tmp_path):
    out = save_dataset(some_refs()[:1], tmp_path / "ds")
    index = json.loads((out / "index.json").read_text())
    index["version"] = 99
    (out / "index.json").write_text(json.dumps(index))
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(out))}: format version 99, expected 1$"):
        ReferenceDataset(out)
    index["version"] = FORMAT_VERSION
    (out / "index.json").write_text(json.dumps(index))
    (out / "splits.json").unlink()
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(out))}: unreadable index or splits \(FileNotFoundError"):
        ReferenceDataset(out)


# ---------------------------------------------------------------------------- property: round trip


def _unit_quats(rng, shape):
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=6)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lengths=st.lists(st.integers(1, 12), min_size=1, max_size=3), seed=st.integers(0, 2**32 - 1),
       keypoints=st.booleans(), residual=st.booleans(), text=st.text(max_size=30),
       fps=st.floats(0.5, 1000.0), meta=st.dictionaries(st.text(max_size=5), json_values, max_size=3))
def test_round_trip_property(lengths, seed, keypoints, residual, text, fps, meta):
    rng = np.random.default_rng(seed)
    lim = joint_limits()
    refs = []
    for i, T in enumerate(lengths):
        pose = np.concatenate([rng.uniform(-1, 1, (T, len(TRACKED_SITES), 3)),
                               _unit_quats(rng, (T, len(TRACKED_SITES)))], axis=-1)
        obj = np.concatenate([rng.uniform(-1, 1, (T, 3)), _unit_quats(rng, (T,))], axis=-1)
        refs.append(Reference(
            hand_joint_pos=rng.uniform(lim[:, 0], lim[:, 1], (T, NUM_JOINTS)), hand_link_pose=pose,
            object_pose=obj, object_name="cube_050", instruction=text + str(i), group_id=int(rng.integers(1 << 40)),
            fps=fps, meta=meta, name=f"r{i}" if i % 2 else "",
            human_keypoints=rng.uniform(-2, 2, (T, NUM_KEYPOINTS, 3)) if keypoints else None,
            retarget_residual=rng.uniform(0, 1, T) if residual and i != 1 else None))
    with tempfile.TemporaryDirectory() as d:
        ds = ReferenceDataset(save_dataset(refs, Path(d) / "ds"))
        assert len(ds) == len(refs) and ds.num_frames == sum(lengths)
        for r, back in zip(refs, ds):
            assert_refs_close(r, back)
            assert back.name == (r.name or back.name)
