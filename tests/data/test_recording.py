"""Tests of the recording format: validation messages, npz/CSV round trips, atomic writes, subsets."""

import json
import os
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from adadex.data.recording import (
    CommandLimitError,
    JointNameError,
    NonFiniteValueError,
    Recording,
    RecordingError,
    RecordingFileError,
    RecordingShapeError,
    TimeAxisError,
    UnknownJointNameError,
    csv_file_name,
    from_csv,
    load_recording,
    to_csv,
)
from adadex.sim.robot import HOME_QPOS, JOINT_NAMES, UnknownJointError, joint_index, joint_limits

JOINTS = ("arm_j2", "if_pip", "th_cmc")


def _fields(S=2, T=40, joints=JOINTS, vel=True, seed=0, dt=0.01, t0=0.0):
    rng = np.random.default_rng(seed)
    lim = joint_limits()[joint_index(joints)]
    cmd = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * rng.uniform(0.1, 0.9, (S, T, len(joints)))
    out = dict(time=t0 + dt * np.arange(T), joint_names=joints, command=cmd,
               joint_pos=cmd + rng.normal(0, 0.01, cmd.shape))
    if vel:
        out["joint_vel"] = rng.normal(0, 1, cmd.shape)
    return out


def make(**kw):
    over = {k: kw.pop(k) for k in list(kw) if k not in ("S", "T", "joints", "vel", "seed", "dt", "t0")}
    return Recording(**{**_fields(**kw), **over})


def assert_bit_equal(a, b):
    assert a.dtype == b.dtype and a.shape == b.shape
    assert a.tobytes() == b.tobytes()


def assert_same(a: Recording, b: Recording, *, files_only=False):
    """Bit-exact equality (``files_only``: only what CSV carries)."""
    for name in ("time", "command", "joint_pos"):
        assert_bit_equal(getattr(a, name), getattr(b, name))
    assert (a.joint_vel is None) == (b.joint_vel is None)
    if a.joint_vel is not None:
        assert_bit_equal(a.joint_vel, b.joint_vel)
    assert a.joint_names == b.joint_names and a.sequence_labels == b.sequence_labels
    if not files_only:
        assert_bit_equal(a.initial_qpos, b.initial_qpos)
        assert a.meta == b.meta
        assert a == b


# ---------------------------------------------------------------------------- construction


def test_defaults_properties_and_immutability():
    f = _fields(S=3, T=11, dt=0.02, t0=5.0)
    rec = Recording(**f)
    assert (rec.num_sequences, rec.num_steps, rec.num_joints) == (3, 11, 3)
    assert rec.dt == pytest.approx(0.02) and rec.duration == pytest.approx(0.2)
    assert rec.sequence_labels == ("seq0", "seq1", "seq2")
    assert rec.joint_indices.tolist() == [JOINT_NAMES.index(j) for j in JOINTS]
    expected_q0 = np.tile(HOME_QPOS, (3, 1))
    expected_q0[:, rec.joint_indices] = f["joint_pos"][:, 0]
    assert_bit_equal(rec.initial_qpos, expected_q0)
    # Copies, read-only: neither the caller's arrays nor the recording can be changed through the other.
    assert not np.shares_memory(rec.command, f["command"])
    with pytest.raises(ValueError, match="read-only"):
        rec.command[0, 0, 0] = 0.0
    f["command"][:] = 0.0
    assert rec.command[0, 0, 0] != 0.0
    assert "3 sequences × 11 steps" in repr(rec) and len(repr(rec)) < 300


def test_initial_qpos_of_shape_22_applies_to_all_sequences():
    rec = make(S=2, initial_qpos=HOME_QPOS)
    assert rec.initial_qpos.shape == (2, 22)
    assert_bit_equal(rec.initial_qpos[1], HOME_QPOS)


def test_meta_is_normalised_through_json():
    rec = make(meta={"seed": np.int64(3), "noise": np.float64(0.001), "sequences": ({"joint": "if_pip"},) * 2})
    assert rec.meta == {"seed": 3, "noise": 0.001, "sequences": [{"joint": "if_pip"}] * 2}
    assert type(rec.meta["seed"]) is int
    with pytest.raises(RecordingError, match="meta: not JSON-serializable"):
        make(meta={"bad": object()})
    with pytest.raises(RecordingError, match="meta: expected a dict, got list"):
        make(meta=[1, 2])


def test_large_absolute_times_are_uniform_enough():
    rec = make(t0=1.7e9, dt=0.002, T=200)
    assert rec.dt == pytest.approx(0.002, rel=1e-5)


# ---------------------------------------------------------------------------- validation messages


@pytest.mark.parametrize("field", ["command", "joint_pos", "joint_vel"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values_name_field_sequence_time_and_joint(field, bad):
    f = _fields(S=3)
    f[field][2, 17, 1] = bad
    f[field][2, 30, 0] = bad
    with pytest.raises(NonFiniteValueError,
                       match=rf"^{field}: non-finite value -?(nan|inf) in sequence 2 \('walk'\) at time index 17 "
                             r"\(t=0\.17 s\), joint 'if_pip'; 2 non-finite values in total"):
        Recording(**f, sequence_labels=("a", "b", "walk"))


def test_non_finite_time():
    f = _fields()
    f["time"][4] = np.nan
    with pytest.raises(NonFiniteValueError, match=r"^time: non-finite value nan at time index 4"):
        Recording(**f)


def test_non_uniform_time_names_the_index():
    f = _fields(T=40)
    f["time"][25:] += 0.003
    with pytest.raises(TimeAxisError, match=r"^time: non-uniform spacing at time index 25: time\[25\] - time\[24\] "
                                            r"= 0\.013\d* s, but the typical spacing is dt = 0\.01"):
        Recording(**f)
    f = _fields(T=40)
    f["time"][10] += 0.01 * 2e-6
    with pytest.raises(TimeAxisError, match="at time index 10"):
        Recording(**f)
    f = _fields(T=40)
    f["time"][10] += 0.01 * 0.5e-6                   # within the 1e-6·dt tolerance
    Recording(**f)


def test_non_increasing_time():
    f = _fields()
    f["time"][7] = f["time"][6]
    with pytest.raises(TimeAxisError, match=r"^time: not strictly increasing at time index 7: time\[7\] = 0\.06"):
        Recording(**f)
    f = _fields()
    f["time"] = f["time"][::-1].copy()
    with pytest.raises(TimeAxisError, match="not strictly increasing at time index 1"):
        Recording(**f)


def test_too_few_samples():
    with pytest.raises(TimeAxisError, match="at least 2 samples, got 1"):
        make(T=1)


@pytest.mark.parametrize("field, shape, pattern", [
    ("joint_pos", (2, 39, 3), r"joint_pos: expected shape \(S, T, J\) = \(2, 40, 3\) .*got \(2, 39, 3\)"),
    ("joint_vel", (2, 40, 2), r"joint_vel: expected shape \(S, T, J\) = \(2, 40, 3\) .*got \(2, 40, 2\)"),
    ("command", (40, 3), r"command: expected 3 dimensions \(S, T, J\), got shape \(40, 3\)"),
    ("command", (0, 40, 3), r"command: a recording needs at least 1 sequence"),
    ("command", (2, 41, 3), r"command: expected shape \(S, T, J\) = \(2, 40, 3\) .*got \(2, 41, 3\)"),
    ("time", (40, 1), r"time: expected shape \(T,\), got \(40, 1\)"),
    ("initial_qpos", (2, 21), r"initial_qpos: expected shape \(S, 22\) = \(2, 22\) .*got \(2, 21\)"),
    ("initial_qpos", (3, 22), r"initial_qpos: expected shape \(S, 22\) = \(2, 22\) .*got \(3, 22\)"),
])
def test_shape_mismatch_says_expected_and_got(field, shape, pattern):
    f = _fields()
    f[field] = np.zeros(shape)
    with pytest.raises(RecordingShapeError, match=pattern):
        Recording(**f)


def test_initial_qpos_nan():
    q = np.tile(HOME_QPOS, (2, 1))
    q[1, 2] = np.nan
    with pytest.raises(NonFiniteValueError, match=r"initial_qpos: non-finite value nan in sequence 1 \('seq1'\) "
                                                  r"for joint 'arm_j3'"):
        make(initial_qpos=q)


def test_unknown_joint_suggests_a_close_match_and_is_an_unknown_joint_error():
    with pytest.raises(UnknownJointNameError, match=r"joint_names\[1\]: unknown joint 'if_pipp'.*did you mean if_pip"):
        make(joint_names=("arm_j2", "if_pipp", "th_cmc"))
    with pytest.raises(UnknownJointError):
        make(joint_names=("arm_j2", "if_pipp", "th_cmc"))
    with pytest.raises(RecordingError):
        make(joint_names=("arm_j2", "if_pipp", "th_cmc"))


def test_bad_joint_name_lists():
    with pytest.raises(JointNameError, match=r"duplicate joint 'if_pip' at positions 0 and 2"):
        make(joint_names=("if_pip", "arm_j2", "if_pip"))
    with pytest.raises(JointNameError, match=r"joint_names: expected a sequence of strings, got the single string"):
        make(joints=("if_pip",), joint_names="if_pip")
    with pytest.raises(JointNameError, match=r"joint_names\[2\]: expected a string, got int"):
        make(joint_names=("if_pip", "arm_j2", 3))
    with pytest.raises(JointNameError, match="at least 1 joint"):
        Recording(time=np.arange(3.0), joint_names=(), command=np.zeros((1, 3, 0)), joint_pos=np.zeros((1, 3, 0)))


@pytest.mark.parametrize("side, offset, word", [(1, 0.01, "above the joint's upper limit 1.885"),
                                                (0, -0.01, "below the joint's lower limit -0.506")])
def test_command_outside_limits_names_joint_sequence_index_value_and_limit(side, offset, word):
    f = _fields()
    lim = joint_limits()[JOINT_NAMES.index("if_pip")]
    f["command"][1, 12, 1] = lim[side] + offset
    f["command"][1, 13, 1] = lim[side] + offset
    value = re.escape(repr(float(lim[side] + offset)))
    with pytest.raises(CommandLimitError,
                       match=rf"^command: {value} rad for joint 'if_pip' in sequence 1 \('seq1'\) at time index 12 "
                             rf"\(t=0\.12 s\) is {word} rad \(tolerance 1e-06 rad\); 2 command values"):
        Recording(**f)
    f["command"][1, 12:14, 1] = lim[side] + np.sign(offset) * 0.9e-6   # within tolerance
    Recording(**f)


def test_measured_positions_may_exceed_limits():
    f = _fields()
    f["joint_pos"][0, 3, 1] = 5.0
    Recording(**f)


def test_sequence_label_errors():
    with pytest.raises(RecordingShapeError, match=r"sequence_labels: expected 2 labels .*got 3"):
        make(sequence_labels=("a", "b", "c"))
    with pytest.raises(RecordingError, match=r"sequence_labels: duplicate label 'a' at sequences 0 and 1"):
        make(sequence_labels=("a", "a"))
    with pytest.raises(RecordingError, match=r"sequence_labels\[1\]: empty label"):
        make(sequence_labels=("a", ""))
    with pytest.raises(RecordingError, match=r"sequence_labels\[0\]: .*control character"):
        make(sequence_labels=("a\x00", "b"))


# ---------------------------------------------------------------------------- npz


def test_npz_round_trip_is_bit_exact(tmp_path):
    rec = make(S=3, sequence_labels=("if_pip/loaded/sine/f1/a0.5", "Ωmega", "seq 2"),
               meta={"seed": 7, "noise_rad": 1e-3, "sequences": [{"k": i} for i in range(3)]})
    path = rec.save(tmp_path / "rec.npz")
    assert path == tmp_path / "rec.npz"
    back = Recording.load(path)
    assert_same(rec, back)
    assert load_recording(path) == rec
    with np.load(path, allow_pickle=False) as z:
        assert set(z.files) == {"time", "joint_names", "command", "joint_pos", "joint_vel", "sequence_labels",
                                "initial_qpos", "meta"}
        assert json.loads(z["meta"].item())["seed"] == 7


def test_npz_round_trip_without_optional_fields(tmp_path):
    rec = make(vel=False)
    back = Recording.load(rec.save(tmp_path / "sub" / "dir" / "r.npz"))
    assert back.joint_vel is None
    assert_same(rec, back)


def test_load_minimal_file_fills_defaults(tmp_path):
    f = _fields(vel=False)
    np.savez(tmp_path / "min.npz", **f)
    rec = Recording.load(tmp_path / "min.npz")
    assert rec.sequence_labels == ("seq0", "seq1") and rec.meta == {}
    assert_bit_equal(rec.initial_qpos[:, rec.joint_indices], f["joint_pos"][:, 0])


@pytest.mark.parametrize("key", ["time", "joint_names", "command", "joint_pos"])
def test_load_missing_required_key_names_key_and_file(tmp_path, key):
    f = _fields()
    del f[key]
    np.savez(tmp_path / "broken.npz", **f)
    with pytest.raises(RecordingFileError, match=rf"broken\.npz: missing required key '{key}'"):
        Recording.load(tmp_path / "broken.npz")


def test_load_errors_name_the_file(tmp_path):
    f = _fields()
    np.savez(tmp_path / "extra.npz", **f, joint_effort=np.zeros(3))
    with pytest.raises(RecordingFileError, match=r"extra\.npz: unexpected key 'joint_effort'"):
        Recording.load(tmp_path / "extra.npz")
    f["command"][1, 5, 2] = np.nan
    np.savez(tmp_path / "nan.npz", **f)
    with pytest.raises(NonFiniteValueError, match=r"nan\.npz: command: non-finite value nan in sequence 1 "
                                                  r"\('seq1'\) at time index 5 \(t=0\.05 s\), joint 'th_cmc'"):
        Recording.load(tmp_path / "nan.npz")
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(RecordingFileError, match=r"junk\.npz: not a readable \.npz recording"):
        load_recording(tmp_path / "junk.npz")
    np.savez(tmp_path / "meta.npz", **_fields(), meta=np.array("[1, 2]"))
    with pytest.raises(RecordingFileError, match=r"meta\.npz: key 'meta' must be a JSON object"):
        Recording.load(tmp_path / "meta.npz")
    with pytest.raises(FileNotFoundError):
        Recording.load(tmp_path / "absent.npz")


def test_save_overwrites_atomically_and_leaves_no_temp_files(tmp_path, monkeypatch):
    path = tmp_path / "rec.npz"
    first = make(seed=1)
    first.save(path)
    make(seed=2).save(path)
    assert os.listdir(tmp_path) == ["rec.npz"]
    assert Recording.load(path) == make(seed=2)

    def savez_then_fail(f, **arrays):
        f.write(b"PK\x03\x04 partial")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", savez_then_fail)
    with pytest.raises(OSError, match="disk full"):
        make(seed=3).save(path)
    assert os.listdir(tmp_path) == ["rec.npz"]
    monkeypatch.undo()
    assert Recording.load(path) == make(seed=2)


def _corrupt(rec: Recording, **fields) -> Recording:
    """A recording whose fields were changed after validation (what ``save`` must still refuse)."""
    for k, v in fields.items():
        object.__setattr__(rec, k, v)
    return rec


def test_bad_input_writes_nothing(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    bad_cmd = make().command.copy()
    bad_cmd[0, 3, 0] = np.nan
    with pytest.raises(NonFiniteValueError, match="command: non-finite value nan in sequence 0"):
        _corrupt(make(), command=bad_cmd).save(out / "r.npz")
    with pytest.raises(NonFiniteValueError):
        to_csv(_corrupt(make(), command=bad_cmd), out / "csv")
    with pytest.raises(RecordingFileError, match="use to_csv"):
        make().save(out / "r.csv")
    with pytest.raises(RecordingError, match="differ only in case"):
        to_csv(make(sequence_labels=("run", "RUN")), out / "csv")
    assert list(out.iterdir()) == []


# ---------------------------------------------------------------------------- CSV


def test_csv_round_trip_is_bit_exact(tmp_path):
    f = _fields(S=3, T=25, t0=-1.25, dt=0.004)
    f["joint_pos"][0, 0, 0] = -0.0
    f["joint_vel"][1, 2, 2] = 1e-300
    f["joint_vel"][2, 3, 1] = 1.2345678901234567e200
    labels = ("if_pip/loaded/sine/f1/a0.5", "50%", "Ωmega run")
    rec = Recording(**f, sequence_labels=labels)
    paths = to_csv(rec, tmp_path / "csv")
    assert [p.name for p in paths] == [csv_file_name(lab) for lab in labels]
    assert paths[0].name == "if_pip%2Floaded%2Fsine%2Ff1%2Fa0.5.csv"
    assert sorted(os.listdir(tmp_path / "csv")) == sorted(p.name for p in paths)
    header = paths[0].read_text().splitlines()[0]
    assert header == ("time,cmd_arm_j2,cmd_if_pip,cmd_th_cmc,pos_arm_j2,pos_if_pip,pos_th_cmc,"
                      "vel_arm_j2,vel_if_pip,vel_th_cmc")
    back = from_csv(paths)
    assert_same(rec, back)
    assert_bit_equal(back.initial_qpos, rec.initial_qpos)           # defaults agree
    assert_bit_equal(np.signbit(back.joint_pos), np.signbit(rec.joint_pos))
    assert_same(rec.subset(sequences=[0]), load_recording(paths[0]))
    assert set(load_recording(tmp_path / "csv").sequence_labels) == set(labels)


def test_csv_directory_loads_in_natural_order(tmp_path):
    rec = make(S=12, T=5, vel=False)
    to_csv(rec, tmp_path)
    assert load_recording(tmp_path).sequence_labels == rec.sequence_labels


def _write(path: Path, header: str, rows) -> Path:
    path.write_text(header + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    return path


def test_from_csv_accepts_any_column_order_comments_and_labels(tmp_path):
    a = _write(tmp_path / "a.csv", "# exported by a logger\ntime, cmd_if_pip, cmd_arm_j2, pos_if_pip, pos_arm_j2",
               [(0.0, 0.1, 0.2, 0.11, 0.21), (0.5, 0.3, 0.4, 0.31, 0.41), (1.0, 0.5, 0.6, 0.51, 0.61)])
    b = _write(tmp_path / "b.csv", "pos_arm_j2,cmd_arm_j2,time,pos_if_pip,cmd_if_pip",
               [(1.21, 1.2, 0.0, 1.11, 1.1), (1.41, 1.4, 0.5, 1.31, 1.3), (1.61, 1.6, 1.0, 1.51, 1.5)])
    rec = from_csv([a, b], label=["first", "second"])
    assert rec.joint_names == ("if_pip", "arm_j2") and rec.sequence_labels == ("first", "second")
    assert rec.command[1].tolist() == [[1.1, 1.2], [1.3, 1.4], [1.5, 1.6]]
    assert rec.joint_pos[0, :, 1].tolist() == [0.21, 0.41, 0.61]
    assert rec.dt == 0.5 and rec.joint_vel is None
    assert from_csv(str(a), label="x").sequence_labels == ("x",)
    with pytest.raises(RecordingError, match="one label 'x' for 2 files"):
        from_csv([a, b], label="x")


@pytest.mark.parametrize("header, rows, error, pattern", [
    ("time,cmd_if_pipp,pos_if_pipp", [(0, 0, 0), (1, 0, 0)], UnknownJointNameError,
     r"bad\.csv: column 'cmd_if_pipp' \(column 2\): unknown joint 'if_pipp'.*did you mean if_pip"),
    ("time,cmd_if_pip,pos_if_pip,torque_if_pip", [(0, 0, 0, 0), (1, 0, 0, 0)], RecordingFileError,
     r"bad\.csv: unexpected column 'torque_if_pip' \(column 4\)"),
    ("t,cmd_if_pip,pos_if_pip", [(0, 0, 0), (1, 0, 0)], RecordingFileError, r"bad\.csv: missing column 'time'"),
    ("time,cmd_if_pip,pos_if_pip,cmd_if_pip", [(0, 0, 0, 0), (1, 0, 0, 0)], RecordingFileError,
     r"bad\.csv: duplicate column 'cmd_if_pip' \(columns 2 and 4\)"),
    ("time,cmd_if_pip,cmd_arm_j2,pos_if_pip", [(0, 0, 0, 0), (1, 0, 0, 0)], RecordingFileError,
     r"bad\.csv: joint 'arm_j2' has column cmd_arm_j2 but no pos_arm_j2"),
    ("time,cmd_if_pip,pos_if_pip", [(0, 0, 0), (1, "abc", 0)], RecordingFileError,
     r"bad\.csv line 3, column 'cmd_if_pip': cannot parse 'abc' as a number"),
    ("time,cmd_if_pip,pos_if_pip", [(0, 0, 0), (1, 0)], RecordingFileError,
     r"bad\.csv line 3: expected 3 values, got 2"),
    ("time,cmd_if_pip,pos_if_pip", [(0, 0, 0), (1, 0, "nan")], NonFiniteValueError,
     r"bad\.csv: joint_pos: non-finite value nan in sequence 0 \('bad'\) at time index 1"),
    ("time,cmd_if_pip,pos_if_pip", [(0, 0, 0), (1, 9, 0)], CommandLimitError,
     r"bad\.csv: command: 9\.0 rad for joint 'if_pip'"),
    ("time,cmd_if_pip,pos_if_pip", [(0, 0, 0)], TimeAxisError, r"bad\.csv: time: .*at least 2 samples, got 1"),
])
def test_csv_errors_name_file_and_column(tmp_path, header, rows, error, pattern):
    path = _write(tmp_path / "bad.csv", header, rows)
    with pytest.raises(error, match=pattern):
        load_recording(path)


def test_csv_files_must_agree(tmp_path):
    good = _write(tmp_path / "a.csv", "time,cmd_if_pip,pos_if_pip", [(0, 0, 0), (1, 0, 0)])
    # (b's dt is 0.5 s: a 2 s sample period is now refused on its own, see SAMPLE_PERIOD_RANGE)
    other_time = _write(tmp_path / "b.csv", "time,cmd_if_pip,pos_if_pip", [(0, 0, 0), (0.5, 0, 0)])
    with pytest.raises(TimeAxisError, match=r"b\.csv: time differs from .*a\.csv at time index 1"):
        from_csv([good, other_time])
    other_joint = _write(tmp_path / "c.csv", "time,cmd_if_dip,pos_if_dip", [(0, 0, 0), (1, 0, 0)])
    with pytest.raises(JointNameError, match=r"c\.csv: joints differ .*missing: if_pip; extra: if_dip"):
        from_csv([good, other_joint])
    with_vel = _write(tmp_path / "d.csv", "time,cmd_if_pip,pos_if_pip,vel_if_pip", [(0, 0, 0, 0), (1, 0, 0, 0)])
    with pytest.raises(RecordingFileError, match=r"d\.csv has vel_ columns but .*a\.csv does not"):
        from_csv([good, with_vel])


# ---------------------------------------------------------------------------- subset, full_command


def test_full_command_holds_unrecorded_joints_at_initial_qpos():
    q0 = np.tile(HOME_QPOS, (2, 1)) + np.array([[0.0], [0.01]])
    rec = make(initial_qpos=q0)
    full = rec.full_command()
    assert full.shape == (2, 40, 22)
    assert_bit_equal(full[:, :, rec.joint_indices], rec.command)
    others = np.setdiff1d(np.arange(22), rec.joint_indices)
    assert_bit_equal(full[:, :, others], np.repeat(q0[:, None, others], 40, axis=1))
    full[0, 0, 0] = 123.0
    assert rec.full_command()[0, 0, 0] != 123.0


def test_subset_sequences_and_joints():
    rec = make(S=4, sequence_labels=("a", "b", "c", "d"), meta={"sequences": [{"i": i} for i in range(4)], "seed": 1})
    sub = rec.subset(sequences=["c", 0, -1], joints=["th_cmc", "arm_j2"])
    assert sub.sequence_labels == ("c", "a", "d") and sub.joint_names == ("th_cmc", "arm_j2")
    assert_bit_equal(sub.command, rec.command[[2, 0, 3]][:, :, [2, 0]])
    assert_bit_equal(sub.joint_pos, rec.joint_pos[[2, 0, 3]][:, :, [2, 0]])
    assert_bit_equal(sub.joint_vel, rec.joint_vel[[2, 0, 3]][:, :, [2, 0]])
    assert_bit_equal(sub.initial_qpos, rec.initial_qpos[[2, 0, 3]])
    assert sub.meta == {"sequences": [{"i": 2}, {"i": 0}, {"i": 3}], "seed": 1}
    assert rec.meta["sequences"][0] == {"i": 0}
    # A dropped joint is held at its initial value.
    pip = JOINT_NAMES.index("if_pip")
    assert np.all(sub.full_command()[:, :, pip] == sub.initial_qpos[:, None, pip])
    assert rec.subset(sequences="b").num_sequences == 1
    assert rec.subset(joints="if_pip").joint_names == ("if_pip",)
    assert rec.subset() == rec


def test_subset_errors():
    rec = make(S=2, sequence_labels=("sine", "chirp"))
    with pytest.raises(RecordingError, match=r"no sequence labelled 'chrip'; did you mean 'chirp'"):
        rec.subset(sequences=["chrip"])
    with pytest.raises(RecordingError, match="index 2 is out of range for 2 sequences"):
        rec.subset(sequences=[2])
    with pytest.raises(RecordingError, match=r"sequence 0 \('sine'\) is selected twice"):
        rec.subset(sequences=[0, "sine"])
    with pytest.raises(RecordingError, match="empty selection"):
        rec.subset(sequences=[])
    with pytest.raises(JointNameError, match=r"'arm_j1' is not recorded \(recorded joints: arm_j2, if_pip, th_cmc\)"):
        rec.subset(joints=["arm_j1"])
    with pytest.raises(UnknownJointNameError, match="did you mean if_pip"):
        rec.subset(joints=["if_pop"])


# ---------------------------------------------------------------------------- property test


@st.composite
def recordings(draw):
    S = draw(st.integers(1, 3))
    T = draw(st.integers(2, 12))
    joints = tuple(draw(st.permutations(JOINT_NAMES))[:draw(st.integers(1, 4))])
    dt = draw(st.floats(1e-4, 0.5))
    t0 = draw(st.floats(-100, 100))
    lim = joint_limits()[joint_index(joints)]
    unit = st.floats(0, 1)
    frac = np.array(draw(st.lists(unit, min_size=S * T * len(joints), max_size=S * T * len(joints))))
    cmd = np.clip(lim[:, 0] + (lim[:, 1] - lim[:, 0]) * frac.reshape(S, T, len(joints)), lim[:, 0], lim[:, 1])
    finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)

    def arr():
        return np.array(draw(st.lists(finite, min_size=cmd.size, max_size=cmd.size))).reshape(cmd.shape)

    labels = draw(st.one_of(
        st.just(()),
        st.lists(st.text(st.characters(blacklist_categories=("Cc", "Cs")), min_size=1, max_size=12),
                 min_size=S, max_size=S, unique_by=lambda s: csv_file_name(s).lower())))
    return Recording(time=t0 + dt * np.arange(T), joint_names=joints, command=cmd, joint_pos=arr(),
                     joint_vel=draw(st.one_of(st.none(), st.builds(arr))), sequence_labels=tuple(labels),
                     meta=draw(st.dictionaries(st.text(max_size=5), st.one_of(st.integers(), st.text(max_size=5)),
                                               max_size=3)))


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rec=recordings())
def test_random_valid_recordings_round_trip(rec):
    with tempfile.TemporaryDirectory() as d:
        assert_same(rec, Recording.load(rec.save(Path(d) / "r.npz")))
        paths = to_csv(rec, Path(d) / "csv")
        assert_same(rec, from_csv(paths), files_only=True)
        assert len(os.listdir(Path(d) / "csv")) == rec.num_sequences
