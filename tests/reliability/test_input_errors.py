"""Bad input, one class per test, as a user meets it: one line on stderr naming the file, field, index or
setting, exit code 2, no traceback, and (``--debug``) an :class:`~adadex.errors.AdadexError`. A bug is
one line and exit code 1 in every subcommand alike (issue 44: one error contract).

Every input is built with numpy in ``tmp_path`` (or is a copy of the session's tiny dataset); nothing
here trains or simulates more than a few steps.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from adadex.cli import main
from adadex.errors import AdadexError, ArrayError

ROOT = Path(__file__).resolve().parents[2]


def fails(argv, capsys, *fragments, code: int = 2, debug: type | None = AdadexError) -> str:
    """Run the command line ``argv`` in-process: exit ``code``, one line on stderr holding every fragment,
    no traceback; with ``--debug`` it raises ``debug``. Returns the line."""
    capsys.readouterr()
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert rc == code, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for f in fragments:
        assert f in err, err
    if debug is not None:
        with pytest.raises(debug):
            main(["--debug", *map(str, argv)])
        capsys.readouterr()
    return err


def recording(tmp: Path, name: str = "rec.npz", S: int = 1, T: int = 30, **extra) -> Path:
    cmd = np.full((S, T, 1), 0.3)
    arrays = {"time": np.arange(T) / 60, "joint_names": np.array(["if_pip"]), "command": cmd, "joint_pos": cmd.copy()}
    arrays.update(extra)
    np.savez(tmp / name, **arrays)
    return tmp / name


def plan(tmp: Path, capsys) -> Path:
    """A one-sequence excitation plan (designed, not simulated)."""
    out = tmp / "plan.npz"
    assert main(["sysid", "excite", "--joints", "if_pip", "--freqs", "1", "--amps", "0.5", "--poses", "loaded",
                 "--kinds", "sine", "--duration", "1", "--out", str(out)]) == 0
    capsys.readouterr()
    return out


# ---------------------------------------------------------------------------- one contract


@pytest.mark.parametrize("argv, module, command", [
    (["data", "info", "DIR"], "adadex.data.cli", "_cmd_info"),
    (["sysid", "compare", "REC"], "adadex.sysid.cli", "_cmd_compare"),
    (["encoder", "eval", "CKPT"], "adadex.train.encoder_cli", "_cmd_eval"),
    (["sim", "export"], "adadex.cli", "_cmd_sim_export"),
])
def test_every_subcommand_reports_by_the_one_contract(argv, module, command, monkeypatch, capsys):
    import importlib

    mod = importlib.import_module(module)
    prog = "adadex " + " ".join(argv[:2])

    def bug(a):
        raise ValueError("a bare ValueError inside adadex")       # a bug, whatever its type

    monkeypatch.setattr(mod, command, bug)
    err = fails(argv, capsys, f"{prog}: internal error (a bug in adadex", code=1, debug=ValueError)
    assert "ValueError: a bare ValueError" in err

    def bad_input(a):
        from adadex.sim.robot import UnknownJointError

        raise UnknownJointError("if_pipx")                          # an input error that is also a KeyError

    monkeypatch.setattr(mod, command, bad_input)
    err = fails(argv, capsys, f"{prog}: error: unknown joint 'if_pipx'")
    assert not err.split("error: ", 1)[1].startswith(("'", '"')), err   # no KeyError quotes


# ---------------------------------------------------------------------------- recordings


def test_meta_sequences_that_disagree_with_the_arrays(tmp_path, capsys):
    meta = json.dumps({"sequences": [{"joint": "if_pip", "label": "a"}]})
    rec = recording(tmp_path, S=2, meta=np.array(meta))
    for cmd in ("compare", "diagnose"):
        fails(["sysid", cmd, rec], capsys, "rec.npz: meta['sequences']: 1 entries", "2 sequences")
    rec = recording(tmp_path, "r2.npz", meta=np.array(json.dumps({"sequences": ["if_pip"]})))
    fails(["sysid", "compare", rec], capsys, "meta['sequences'][0]: expected an object")


@pytest.mark.parametrize("value", [1e6, 1e200, 57.3])
def test_measured_positions_outside_a_physical_range(value, tmp_path, capsys):
    pos = np.full((1, 30, 1), 0.3)
    pos[0, 5, 0] = value
    rec = recording(tmp_path, joint_pos=pos)
    err = fails(["sysid", "compare", rec], capsys, "joint_pos: ", "joint 'if_pip'", "sequence 0", "time index 5",
                "outside the physical range")
    assert "inf" not in err


def test_model_without_the_recorded_joints_names_the_joints(tmp_path, capsys):
    model = tmp_path / "finger.xml"
    model.write_text('<mujoco><worldbody><body><joint name="j1" type="hinge" range="-1 1"/><geom size=".01"/>'
                     '</body></worldbody><actuator><position joint="j1" kp="10"/></actuator></mujoco>')
    p = plan(tmp_path, capsys)                       # carries initial_qpos for the 22 joints of adadex's robot
    for cmd in (["compare", p], ["simulate", p, "--out", tmp_path / "r.npz"]):
        err = fails(["sysid", *cmd, "--model", model], capsys, "joint_names[0]: unknown joint 'if_pip'", "j1")
        assert "initial_qpos" not in err


# ---------------------------------------------------------------------------- sysid options and patches


def test_excite_freqs_that_are_not_numbers(tmp_path, capsys):
    fails(["sysid", "excite", "--joints", "if_pip", "--freqs", "abc", "--out", tmp_path / "p.npz"], capsys,
          "--freqs: expected comma-separated numbers", "'abc'")
    fails(["sysid", "excite", "--joints", "if_pip", "--amps", "nan", "--out", tmp_path / "p.npz"], capsys,
          "amps: expected finite numbers")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("joint, fragment", [("if_pipx", "joints: unknown joint 'if_pipx'"),
                                             ("if_dip", "joints: 'if_dip' is not recorded")])
def test_diagnose_joints_that_are_unknown_or_unrecorded(joint, fragment, tmp_path, capsys):
    fails(["sysid", "diagnose", recording(tmp_path), "--joints", joint, "--threads", "1"], capsys, fragment)


@pytest.mark.parametrize("noise", ["nan", "inf", "-1"])
def test_simulate_noise_that_is_not_a_noise_level(noise, tmp_path, capsys):
    p = plan(tmp_path, capsys)
    err = fails(["sysid", "simulate", p, "--noise", noise, "--out", tmp_path / "r.npz"], capsys,
                "noise: the sensor noise std must be a finite number ≥ 0")
    assert "joint_pos" not in err and not (tmp_path / "r.npz").exists()


def test_patch_joints_given_as_a_string(tmp_path, capsys):
    patch = tmp_path / "p.json"
    patch.write_text(json.dumps({"effects": [{"effect": "damping", "joints": "if_pip", "params": {"damping": 0.1}}]}))
    fails(["sysid", "compare", recording(tmp_path), "--patch", patch], capsys,
          "p.json: effects[0]: damping: 'joints' must be a non-empty list of joint names", 'got "if_pip"')


def test_excite_csv_out_onto_a_folder_of_user_files(tmp_path, capsys):
    (tmp_path / "plan").mkdir()
    (tmp_path / "plan" / "mine.txt").write_text("mine")
    fails(["sysid", "excite", "--joints", "if_pip", "--out", tmp_path / "plan.csv"], capsys,
          "plan exists and is a folder that is not an adadex output")
    assert [p.name for p in (tmp_path / "plan").iterdir()] == ["mine.txt"]


def test_stale_temporaries_of_a_killed_write_are_removed_by_the_next(tmp_path, capsys):
    from adadex.sim.model_source import BUILTIN_ID
    from adadex.sysid.diagnose import Diagnosis

    diag = tmp_path / "D"
    diag.mkdir()
    Diagnosis(verdict="nothing_missing", baseline_error={}, hypotheses=[], selected=[], explained_fraction={},
              findings=[], wall_time_s=0.0, train_only_joints=[], model=BUILTIN_ID).save(diag)
    out = tmp_path / "patch.json"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()                  # a process id that has ended
    stale = [tmp_path / f".patch.json.p{dead}.{'ab' * 6}.tmp",      # what a killed `sysid fit` leaves
             tmp_path / f".patch.json.{'cd' * 6}.tmp"]               # … and an earlier adadex left
    live = tmp_path / f".patch.json.p{os.getpid()}.{'ef' * 6}.tmp"  # a write still running: kept
    for p in (*stale, live):
        p.write_text('{"effects": [')
    rec = recording(tmp_path)
    assert main(["sysid", "fit", str(rec), "--accept", str(diag), "--out", str(out)]) == 0
    assert json.loads(out.read_text())["effects"] == []
    assert not any(p.exists() for p in stale) and live.exists()


# ---------------------------------------------------------------------------- datasets


def _damaged(tmp: Path, ds: Path, how: str) -> Path:
    folder = Path(shutil.copytree(ds, tmp / "ds"))
    f = folder / "frames" / "hand_joint_pos.memmap"
    if how == "missing":
        f.unlink()
    elif how == "truncated":
        f.write_bytes(f.read_bytes()[:1000])
    else:
        m = np.memmap(f, dtype=np.float32, mode="r+")
        m[100] = np.nan
        m.flush()
        del m
    return folder


@pytest.mark.parametrize("how, fragment", [("missing", "hand_joint_pos.memmap: missing"),
                                           ("truncated", "hand_joint_pos.memmap: 1000 bytes"),
                                           ("nan", "hand_joint_pos: non-finite")])
def test_data_info_on_a_damaged_dataset(how, fragment, tmp_path, tiny_dataset, capsys):
    fails(["data", "info", _damaged(tmp_path, Path(tiny_dataset), how)], capsys, fragment)


@pytest.mark.parametrize("index", [99, -99])
def test_data_show_index_past_the_references(index, tmp_path, tiny_dataset, capsys):
    fails(["data", "show", tiny_dataset, "--index", index, "--no-render", "--out", tmp_path / "r.png"], capsys,
          f"reference index {index} out of range for a dataset of")
    assert not (tmp_path / "r.png").exists()


@pytest.mark.parametrize("limit", ["0", "-1"])
def test_data_build_limit_below_one(limit, tmp_path, monkeypatch, capsys):
    import adadex.data.build as build

    def no_work(*a, **k):
        raise AssertionError("the build started")

    monkeypatch.setattr(build, "build_dataset", no_work)
    fails(["data", "build", "--preset", "tiny", "--limit", limit, "--out", tmp_path / "ds"], capsys,
          f"--limit must be an integer ≥ 1, got {limit}")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("arrays, fragment", [
    ({"fps": np.array([30.0, 60.0])}, "take.npz: fps: expected one number"),
    ({"fps": np.array(1e-9)}, "take.npz: fps: expected a frame rate in [1, 10000] Hz"),
    ({"keypoints": np.zeros((0, 21, 3)), "object_pose": np.zeros((0, 7))}, "take.npz: keypoints: 0 frame(s)"),
])
def test_data_import_fps_arrays_and_zero_frames(arrays, fragment, tmp_path, capsys):
    take = {"keypoints": np.zeros((40, 21, 3)), "object_pose": np.tile([0, 0, 0, 1.0, 0, 0, 0], (40, 1)), **arrays}
    np.savez(tmp_path / "take.npz", **take)
    fails(["data", "import", tmp_path / "take.npz", "--object", "cube_050", "--out", tmp_path / "out"], capsys,
          fragment)
    assert not (tmp_path / "out").exists()


def test_sim_export_onto_a_folder(tmp_path, capsys):
    (tmp_path / "dir").mkdir()
    fails(["sim", "export", "--out", tmp_path / "dir"], capsys, "dir is a folder")
    assert not list((tmp_path / "dir").iterdir())


# ---------------------------------------------------------------------------- the environment


@pytest.mark.parametrize("batch, shape", [((3,), (3, 22)), ((), (22,))])
def test_env_step_action_of_another_batch_shape(batch, shape, tiny_dataset):
    import torch
    from tensordict import TensorDict

    from adadex.envs.tracking import TrackingEnv

    env = TrackingEnv(tiny_dataset, num_worlds=2, latent_fn=lambda name: np.zeros(64, np.float32), nthread=1)
    env.reset()
    with pytest.raises(ArrayError, match=rf"action: expected shape \(2, 22\), got {re_shape(shape)}"):
        env.step(TensorDict({"action": torch.zeros(shape)}, batch_size=batch))
    with pytest.raises(ArrayError, match=r"action: missing"):
        env.step(TensorDict({}, batch_size=[2]))


def re_shape(shape) -> str:
    import re

    return re.escape(str(tuple(shape)))


# ---------------------------------------------------------------------------- recipes


@pytest.mark.parametrize("setting, fragment", [
    ("channels=R+X", "channels=R+X: unknown modulation channel(s) ['X']"),
    ("split=unseen_objekt", "no split 'unseen_objekt'"),
    ("max_worlds=0", "max_worlds must be an integer ≥ 1, got 0"),
])
def test_evaluate_recipe_bad_settings(setting, fragment, tmp_path, tiny_dataset):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "WANDB_MODE": "disabled"}
    r = subprocess.run([sys.executable, str(ROOT / "recipes" / "evaluate.py"), f"dataset={tiny_dataset}",
                        "build_preset=null", "smoothness=false", f"out={tmp_path / 'out'}",
                        f"hydra.run.dir={tmp_path / 'hydra'}", setting],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    err = r.stderr.strip()
    assert r.returncode == 2, err[-2000:]
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err[-2000:]
    assert err.startswith("recipes/evaluate.py: error: ") and fragment in err, err
    assert not (tmp_path / "out").exists()
