"""The reliability catalogue: bad inputs as a user meets them, one table.

Each row is an input (files prepared in a fresh folder, then a command line, a Python call or a
recipe), the error class and a fragment of its one-line message, and the promise that nothing on
disk changed: the folder is hashed before and after (so a read that "repairs" a file, a refused
--out that was replaced anyway, or a temporary left behind all fail the row). Command lines are
also checked for exit code ≠ 0, one line on stderr and no traceback, and rerun with ``--debug``
to check the error class. Add a row when a new case is found.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from adadex.cli import main
from adadex.data.recording import CommandLimitError, Recording, RecordingFileError, TimeAxisError
from adadex.data.reference import (
    DatasetError,
    JointLimitError,
    QuaternionNormError,
    ReferenceDataset,
    ReferenceError,
    ReferenceValueError,
)
from adadex.errors import AdadexError, ArrayError, ConfigError
from adadex.io import OutputExistsError
from adadex.sim.patch import PatchError
from adadex.sim.robot import HOME_QPOS
from adadex.sysid.cli import CliError
from adadex.sysid.diagnose import DiagnosisError

ROOT = Path(__file__).resolve().parents[2]


# ---------------------------------------------------------------------------- inputs


def user_folder(tmp: Path, name: str = "mine") -> Path:
    d = tmp / name
    d.mkdir()
    (d / "thesis.tex").write_text("three years of work")
    return d


def good_recording(tmp: Path, T: int = 30, name: str = "rec.npz") -> Path:
    cmd = np.full((1, T, 1), 0.3)
    Recording(time=np.arange(T) / 60, joint_names=("if_pip",), command=cmd, joint_pos=cmd).save(tmp / name)
    return tmp / name


def recording_arrays(T: int = 30, dt: float = 1 / 60) -> dict:
    cmd = np.full((1, T, 1), 0.3)
    return {"time": np.arange(T) * dt, "joint_names": np.array(["if_pip"]), "command": cmd, "joint_pos": cmd}


def npz(tmp: Path, name: str, **arrays) -> Path:
    np.savez(tmp / name, **arrays)
    return tmp / name


def truncated(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def dataset_copy(tmp: Path, ds: Path) -> Path:
    return Path(shutil.copytree(ds, tmp / "ds"))


def corrupt_frame(folder: Path, key: str, change: Callable[[np.ndarray], None]) -> tuple[int, str]:
    """Change frame 3 of the episode window of the first training reference, on disk; returns (index, name)."""
    ds = ReferenceDataset(folder)
    i = ds.split("unseen_trajectory", "train")[0]
    e = ds.entries[i]
    meta = json.loads((folder / "frames" / "meta.json").read_text())
    shape = tuple(meta[key]["shape"])
    m = np.memmap(folder / "frames" / f"{key}.memmap", dtype=np.float32, mode="r+", shape=shape)
    change(m[e["offset"] + e["window_start"] + 3])
    m.flush()
    del m
    return i, e["name"]


def bad_frame_env(key, change):
    def make(tmp, ds):
        folder = dataset_copy(tmp, ds)
        corrupt_frame(folder, key, change)
        return lambda: _env(folder)
    return make


def bad_frame_item(key, change):
    """``ds[i]`` of the reference whose frame ``change`` corrupted."""
    def make(tmp, ds):
        folder = dataset_copy(tmp, ds)
        i = corrupt_frame(folder, key, change)[0]
        return lambda: ReferenceDataset(folder)[i]
    return make


def _env(folder, **kw):
    from adadex.envs.tracking import TrackingEnv

    return TrackingEnv(folder, latent_fn=lambda name: np.zeros(64, np.float32), nthread=1, **kw)


def _nan(a):
    a[0] = np.nan


def _times3(a):
    a[3:] *= 3


def _zero_quat(a):
    a[3:] = 0


def _joint25(a):
    a[5] = 25.0


def _step_wrong_action(folder):
    import torch

    env = _env(folder, num_worlds=2)
    td = env.reset()
    td["action"] = torch.zeros(2, 21)
    env.step(td)


# ---------------------------------------------------------------------------- the table


@dataclass(frozen=True)
class Case:
    id: str
    make: Callable          # (tmp folder, tiny dataset folder) -> argv list | zero-arg callable | ("recipe", [...])
    error: type
    fragment: str


CASES = [
    # --- no user data lost: an --out that is not an adadex output of the same kind is refused
    Case("data import onto a folder of user files",
         lambda t, ds: ["data", "import", str(npz(t, "a.npz", x=np.zeros(1))), "--object", "cube_050",
                        "--out", str(user_folder(t))], OutputExistsError, "not an adadex output"),
    Case("data import onto a file",
         lambda t, ds: (t / "notes.txt").write_text("notes") and
         ["data", "import", str(npz(t, "a.npz", x=np.zeros(1))), "--out", str(t / "notes.txt")],
         OutputExistsError, "is a file"),
    Case("data build onto a folder of user files",
         lambda t, ds: ["data", "build", "--preset", "tiny", "--out", str(user_folder(t))],
         OutputExistsError, "refusing to replace it with a dataset"),
    Case("sysid compare onto a folder of user files",
         lambda t, ds: ["sysid", "compare", str(good_recording(t)), "--out", str(user_folder(t))],
         OutputExistsError, "pass --force"),
    Case("sysid compare onto a diagnosis folder",
         lambda t, ds: (user_folder(t, "D") / ".adadex-output.json").write_text('{"kind": "diagnosis"}') and
         ["sysid", "compare", str(good_recording(t)), "--out", str(t / "D")],
         OutputExistsError, "an adadex diagnosis output"),
    Case("sysid diagnose onto a folder of user files",
         lambda t, ds: ["sysid", "diagnose", str(good_recording(t)), "--out", str(user_folder(t))],
         OutputExistsError, "not an adadex output"),
    Case("sysid report onto a user file",
         lambda t, ds: (t / "index.html").write_text("<html>my page</html>") and
         ["sysid", "report", str(good_recording(t)), "--out", str(t / "index.html")],
         OutputExistsError, "is a file"),
    Case("sysid fit onto a user file",
         lambda t, ds: (t / "notes.json").write_text('{"mine": 1}') and
         ["sysid", "fit", str(good_recording(t)), "--add", "damping:if_pip", "--out", str(t / "notes.json")],
         OutputExistsError, "is a file"),
    Case("save_dataset onto a folder of user files",
         lambda t, ds: (lambda out: lambda: __import__("adadex.data.reference", fromlist=["x"]).save_dataset(
             list(ReferenceDataset(ds))[:1], out))(user_folder(t)),
         OutputExistsError, "force=True"),
    # --- reading never writes: truncated or missing frame files are named, never grown back
    Case("truncated frames memmap (API)",
         lambda t, ds: (lambda f: (truncated(f / "frames" / "object_pose.memmap"),
                                   lambda: ReferenceDataset(f).frames)[1])(dataset_copy(t, ds)),
         DatasetError, "object_pose.memmap: "),
    Case("truncated frames memmap (data show)",
         lambda t, ds: (lambda f: (truncated(f / "frames" / "hand_joint_pos.memmap"),
                                   ["data", "show", str(f), "--no-render", "--out", str(t / "ref.png")])[1])(
             dataset_copy(t, ds)), DatasetError, "hand_joint_pos.memmap: "),
    Case("missing frames memmap",
         lambda t, ds: (lambda f: ((f / "frames" / "hand_link_pose.memmap").unlink(),
                                   lambda: ReferenceDataset(f)[0])[1])(dataset_copy(t, ds)),
         DatasetError, "hand_link_pose.memmap: missing"),
    # --- one validation of reference frames, in ds[i] and in TrackingEnv (up front, naming reference and frame)
    Case("NaN in a reference: TrackingEnv", bad_frame_env("object_pose", _nan), ReferenceValueError,
         "frame "),
    Case("NaN in a reference: ds[i]", bad_frame_item("hand_joint_pos", _nan), ReferenceValueError,
         "hand_joint_pos: non-finite"),
    Case("object quaternion x3: TrackingEnv", bad_frame_env("object_pose", _times3), QuaternionNormError,
         "object_pose: quaternion norm 3.0"),
    Case("object quaternion x3: ds[i]", bad_frame_item("object_pose", _times3), QuaternionNormError,
         "quaternion norm 3.0"),
    Case("zero object quaternion: TrackingEnv", bad_frame_env("object_pose", _zero_quat), QuaternionNormError,
         "quaternion norm 0.0"),
    Case("joint at 25 rad: TrackingEnv", bad_frame_env("hand_joint_pos", _joint25), JointLimitError,
         "is +25.0000 rad, outside"),
    Case("num_worlds=2.5", lambda t, ds: lambda: _env(ds, num_worlds=2.5), ConfigError,
         "num_worlds must be an integer ≥ 1, got 2.5"),
    Case("split as a plain string", lambda t, ds: lambda: _env(ds, split="unseen_trajectory"), DatasetError,
         "split: expected (name, part)"),
    Case("action of the wrong shape", lambda t, ds: lambda: _step_wrong_action(ds), ArrayError,
         "action: expected shape (2, 22), got (2, 21)"),
    # --- recordings
    Case("initial_qpos outside the joint limits",
         lambda t, ds: ["sysid", "compare", str(npz(t, "r.npz", **recording_arrays(),
                                                    initial_qpos=np.r_[HOME_QPOS[:1] + 9, HOME_QPOS[1:]][None]))],
         CommandLimitError, "initial_qpos: "),
    Case("time in milliseconds",
         lambda t, ds: ["sysid", "compare", str(npz(t, "r.npz", **recording_arrays(dt=16.7)))],
         TimeAxisError, "is it in milliseconds?"),
    Case("dt = 1e-12 s",
         lambda t, ds: ["sysid", "diagnose", str(npz(t, "r.npz", **recording_arrays(dt=1e-12)))],
         TimeAxisError, "sample period dt = 1e-12 s is outside the plausible range"),
    Case("truncated recording .npz",
         lambda t, ds: ["sysid", "compare", str(truncated(good_recording(t)))],
         RecordingFileError, "rec.npz: "),
    Case("corrupt import .npz",
         lambda t, ds: ["data", "import", str(truncated(npz(t, "take.npz", keypoints=np.zeros((40, 21, 3)),
                                                              object_pose=np.zeros((40, 7))))),
                        "--object", "cube_050", "--out", str(t / "out")],
         ReferenceError, "take.npz: cannot read as .npz"),
    # --- sysid inputs that used to end in a traceback
    Case("corrupt diagnosis.json",
         lambda t, ds: (user_folder(t, "D") / "diagnosis.json").write_text('{"verdict": "expl') and
         ["sysid", "fit", str(good_recording(t)), "--accept", str(t / "D"), "--out", str(t / "p.json")],
         DiagnosisError, "diagnosis.json: not a readable diagnosis"),
    Case("non-UTF-8 patch",
         lambda t, ds: (t / "p.json").write_bytes(b"\xff\xfe{") and
         ["sysid", "compare", str(good_recording(t)), "--patch", str(t / "p.json")],
         CliError, "p.json: not a readable model patch"),
    Case("folder as a patch",
         lambda t, ds: ["sysid", "compare", str(good_recording(t)), "--patch", str(user_folder(t, "p"))],
         CliError, "not a readable model patch (IsADirectoryError"),
    Case('"abc" as a patch value',
         lambda t, ds: (t / "p.json").write_text(json.dumps(
             {"effects": [{"effect": "damping", "joints": ["if_pip"], "params": {"damping": "abc"}}]})) and
         ["sysid", "compare", str(good_recording(t)), "--patch", str(t / "p.json")],
         CliError, "could not convert string to float"),
    Case("unknown patch file", lambda t, ds: ["sysid", "compare", str(good_recording(t)), "--patch",
                                              str(t / "nope.json")], PatchError, "no such patch file"),
    # --- recipes
    Case("recipe with a missing checkpoint",
         lambda t, ds: ("recipe", [ROOT / "recipes/evaluate.py", f"dataset={ds}", "build_preset=null",
                                   f"tracker={t / 'missing.pt'}", f"out={t / 'x'}",
                                   f"hydra.run.dir={t.parent / 'hydra'}"]),   # Hydra's own log folder
         FileNotFoundError, "missing.pt: no such checkpoint file"),
]


# ---------------------------------------------------------------------------- the check


def snapshot(folder: Path) -> dict:
    """Every path under ``folder`` with the hash of its content (folders: None)."""
    out = {}
    for root, dirs, files in os.walk(folder):
        for d in dirs:
            out[os.path.relpath(os.path.join(root, d), folder)] = None
        for f in files:
            p = os.path.join(root, f)
            out[os.path.relpath(p, folder)] = hashlib.sha1(Path(p).read_bytes()).hexdigest()
    return out


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_catalogue(case, tmp_path, tiny_dataset, capsys):
    work = tmp_path / "work"
    work.mkdir()
    run = case.make(work, Path(tiny_dataset))
    before, ds_before = snapshot(work), snapshot(tiny_dataset)
    if isinstance(run, tuple) and run[0] == "recipe":
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        r = subprocess.run([sys.executable, *map(str, run[1])], cwd=work, capture_output=True, text=True,
                           timeout=300, env=env)
        assert r.returncode != 0
        assert case.fragment in r.stderr and "Traceback" not in r.stderr, r.stderr[-2000:]
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    elif isinstance(run, list):
        capsys.readouterr()
        rc = main(run)
        err = capsys.readouterr().err
        assert rc not in (0, None), err
        assert case.fragment in err and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1, err
        assert snapshot(work) == before, "the failed command changed files"
        with pytest.raises(case.error) as info:         # --debug: the traceback, of the expected class
            main(["--debug", *run])
        assert case.fragment in str(info.value)
    else:
        with pytest.raises(case.error) as info:
            run()
        assert case.fragment in str(info.value), str(info.value)
    assert issubclass(case.error, AdadexError) or case.error is FileNotFoundError
    assert snapshot(work) == before, "files changed on disk"
    assert snapshot(tiny_dataset) == ds_before
