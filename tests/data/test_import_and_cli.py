"""Import of external human–object data, and the `adadex data` commands."""

import json

import numpy as np
import pytest

from adadex.cli import main
from adadex.data.hoi_import import ImportRejected, import_npz, resample
from adadex.data.reference import ReferenceDataset, ReferenceError, ReferenceShapeError, ReferenceValueError
from adadex.data.synth import NoiseConfig, Synthesizer, make_instruction
from adadex.sim.scene import CONTROL_HZ


@pytest.fixture(scope="module")
def motion():
    """A clean synthesized motion the robot can follow: keypoints + object poses at 12 Hz."""
    from adadex.data.retarget import Retargeter

    synth, rt = Synthesizer(NoiseConfig.clean()), Retargeter()
    for seed in range(10):
        m = synth.synthesize(make_instruction("lift", "cube_050", seed=seed), seed=0)
        if rt.retarget(m.keypoints).palm_error.max() < 0.03:
            return m
    raise AssertionError("no reachable lift motion among 10 seeds")


def _upsample(m, fps):
    """The motion at a higher frame rate (what a capture system would record)."""
    t12 = np.arange(len(m.keypoints)) / CONTROL_HZ
    t = np.arange(int(t12[-1] * fps) + 1) / fps
    kp = np.stack([np.stack([np.interp(t, t12, m.keypoints[:, j, k]) for k in range(3)], -1) for j in range(21)], 1)
    pos = np.stack([np.interp(t, t12, m.object_pose[:, k]) for k in range(3)], -1)
    from adadex.geometry import quat, rotation
    from scipy.spatial.transform import Slerp

    rot = Slerp(t12, rotation(m.object_pose[:, 3:]))(t)
    return kp, np.concatenate([pos, quat(rot)], 1)


def test_resample_round_trip(motion):
    kp30, obj30 = _upsample(motion, 30.0)
    kp, obj = resample(kp30, obj30, 30.0)
    n = min(len(kp), len(motion.keypoints))
    assert abs(len(kp) - len(motion.keypoints)) <= 1
    assert np.abs(kp[:n] - motion.keypoints[:n]).max() < 2e-3
    assert np.allclose(np.linalg.norm(obj[:, 3:], axis=1), 1.0)


def test_import_npz_retargets_and_resamples(tmp_path, motion):
    kp30, obj30 = _upsample(motion, 30.0)
    f = tmp_path / "take.npz"
    np.savez(f, keypoints=kp30, object_pose=obj30, fps=30.0, object_name="cube_050", instruction="place the cube")
    ref = import_npz(f)
    assert ref.fps == CONTROL_HZ and abs(ref.num_frames - len(motion.keypoints)) <= 1
    assert ref.object_name == "cube_050" and ref.instruction == "place the cube"
    assert ref.human_keypoints.shape == (ref.num_frames, 21, 3)
    assert ref.retarget_residual.shape == (ref.num_frames,) and np.median(ref.retarget_residual) < 0.03
    assert ref.meta["source_fps"] == 30.0
    ref.validate()


def test_import_rejects_two_hands(tmp_path, motion):
    f = tmp_path / "two.npz"
    np.savez(f, keypoints=np.stack([motion.keypoints] * 2, 1), object_pose=motion.object_pose, object_name="cube_050")
    with pytest.raises(ImportRejected, match="2 hands") as e:
        import_npz(f)
    assert e.value.rejection.reason == "two_hands"


@pytest.mark.parametrize("case, error, message", [
    ("nan", ReferenceValueError, "non-finite value at frame 5"),
    ("shape", ReferenceShapeError, r"expected shape \(T, 21, 3\)"),
    ("object_len", ReferenceShapeError, "object_pose: expected shape"),
    ("quat", ReferenceError, "quaternion at frame 7 has norm"),
    ("missing", ReferenceError, "missing array 'object_pose'"),
    ("no_object", ReferenceError, "no object_name"),
])
def test_import_bad_files(tmp_path, motion, case, error, message):
    kp, obj = motion.keypoints.copy(), motion.object_pose.copy()
    arrays = {"keypoints": kp, "object_pose": obj, "object_name": "cube_050"}
    if case == "nan":
        kp[5, 3, 1] = np.nan
    elif case == "shape":
        arrays["keypoints"] = kp[:, :20]
    elif case == "object_len":
        arrays["object_pose"] = obj[:-1]
    elif case == "quat":
        obj[7, 3:] *= 1.1
    elif case == "missing":
        del arrays["object_pose"]
    elif case == "no_object":
        del arrays["object_name"]
    f = tmp_path / f"{case}.npz"
    np.savez(f, **arrays)
    with pytest.raises(error, match=message):
        import_npz(f)


def test_import_not_an_npz(tmp_path):
    f = tmp_path / "x.npz"
    f.write_text("hello")
    with pytest.raises(ReferenceError, match="cannot read as .npz"):
        import_npz(f)


def test_cli_data_build_info_show(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["data", "build", "--preset", "tiny", "--limit", "2", "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "references accepted" in text and "wrote" in text
    ds = ReferenceDataset(out)
    assert ds.info["preset"] == "tiny" and len(ds) >= 1
    assert main(["data", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["references"] == len(ds) and set(info["splits"]) == {"unseen_trajectory", "unseen_object"}
    speed = info["arm_speed"]                    # checked against the stored frames of each episode window
    from adadex.envs.tracking import TrackingConfig, episode_references
    windows = episode_references(ds, None, TrackingConfig().window)
    fastest = [np.abs(np.diff(np.asarray(ds[r].hand_joint_pos)[ds.entries[r]["window_start"]:][:300, :6], axis=0)).max()
               for r in windows]
    assert speed["windows"] == len(windows) and speed["faster"] == sum(f > 0.1 for f in fastest)
    if windows:
        assert speed["fastest"] == pytest.approx(max(fastest), abs=1e-6)
    png = tmp_path / "ref.png"
    assert main(["data", "show", str(out), "--index", "0", "--out", str(png), "--no-render"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_data_info_says_where_the_hand_reaches_into_the_object_before_the_grasp(tmp_path, capsys):
    """A reference whose object lies on the resting hand's index fingertip from frame 50, before its
    grasp (frame 100), is counted; one whose object stays on the table is not, nor is the overlap
    after the grasp frame."""
    import mujoco

    from adadex.data.reference import Reference, save_dataset
    from adadex.sim.robot import HOME_QPOS
    from adadex.sim.scene import build_scene_model

    m = build_scene_model(None)
    d = mujoco.MjData(m)
    d.qpos[:22] = HOME_QPOS
    mujoco.mj_kinematics(m, d)
    table, tip = [0.45, 0.0, 0.026, 1, 0, 0, 0], [*d.site("index_tip").xpos, 1, 0, 0, 0]
    T, q = 320, np.tile(HOME_QPOS, (320, 1))

    def ref(name, on_tip_from, grasp):
        pose = np.tile(table, (T, 1))
        pose[on_tip_from:] = tip
        return Reference.from_joint_positions(q, pose, object_name="cube_050", instruction="wait", group_id=0,
                                              name=name, meta={"phases": {"grasp": grasp}})

    out = save_dataset([ref("clear", T, 100), ref("inside", 50, 100), ref("after", 150, 100)], tmp_path / "ds")
    assert main(["data", "info", str(out), "--json"]) == 0
    inside = json.loads(capsys.readouterr().out)["approach_overlap"]
    assert inside["windows"] == 3 and inside["deeper"] == 1 and inside["deepest_reference"] == "inside"
    assert inside["deepest"] > 0.01
    assert main(["data", "info", str(out)]) == 0
    assert "into the object before the grasp in 1 of 3 episode windows" in capsys.readouterr().out


def test_cli_data_errors(tmp_path, capsys):
    assert main(["data", "info", str(tmp_path / "nothing")]) == 2
    assert "not a reference dataset" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    np.savez(bad, keypoints=np.zeros((20, 21, 3)))
    assert main(["data", "import", str(bad), "--object", "cube_050", "--out", str(tmp_path / "o")]) == 2
    assert "missing array 'object_pose'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
