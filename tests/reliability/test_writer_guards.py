"""Every CLI writer guards its output with the one guard (:mod:`adadex.io`): an existing ``--out`` is
replaced only when it is an earlier output of the same command — recognized by the marker that command
wrote, never by the shape of the content — or with ``--force``; otherwise one line naming the path and
``--force``, exit code 2, nothing written, and no work started.

Covered here: ``sim export [--robot-only] --out``, ``sysid demo --out`` (refusal only: the demo takes
a minute), ``encoder eval --out``; ``sysid excite`` and ``sysid simulate`` in
``test_sysid_writer_guards.py``. Each refusal runs with the command's work replaced by a trap, so
"checked before any work" is tested, not assumed.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from adadex.cli import main
from adadex.resources import asset

def _tree(folder: Path) -> dict:
    """Every file under ``folder`` (hidden ones included) → its SHA-256."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _refused(argv, path: Path, capsys, root: Path) -> None:
    """``argv`` exits 2 with one line naming ``path`` and --force, and changes nothing under ``root``."""
    before = _tree(root)
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(path) in err and "--force" in err, err
    assert _tree(root) == before


def _trap(monkeypatch, module: str, name: str) -> None:
    """Make ``module.name`` (the command's work) fail the test if it is reached."""
    def work(*a, **k):
        raise AssertionError(f"{module}.{name} ran: the output was not checked before the work")
    monkeypatch.setattr(f"{module}.{name}", work)


# ------------------------------------------------------------------------------------------ sim export


@pytest.mark.parametrize("robot_only", [[], ["--robot-only"]], ids=["world", "robot-only"])
def test_sim_export_guards_its_file(tmp_path, capsys, monkeypatch, robot_only):
    mine = tmp_path / "my_robot.xml"
    mine.write_text("<mujoco model='mine'/>")
    with monkeypatch.context() as m:
        _trap(m, "adadex.sim.model_source", "export_world")
        _trap(m, "adadex.sim.robot", "export_mjcf")
        _refused(["sim", "export", *robot_only, "--out", str(mine)], mine, capsys, tmp_path)

    out = tmp_path / "world.xml"
    assert main(["sim", "export", *robot_only, "--out", str(out)]) == 0
    first = out.read_text()
    assert main(["sim", "export", *robot_only, "--out", str(out)]) == 0      # its own earlier output: replaced
    assert out.read_text() == first
    out.write_text(first.replace("<mujoco", "<!-- my edit -->\n<mujoco", 1))  # edited since: the user's now
    _refused(["sim", "export", *robot_only, "--out", str(out)], out, capsys, tmp_path)

    assert main(["sim", "export", *robot_only, "--out", str(mine), "--force"]) == 0
    assert mine.read_text() == first
    assert main(["sim", "export", *robot_only, "--out", str(mine)]) == 0     # now an earlier export


def test_sim_export_onto_a_folder_is_one_line(tmp_path, capsys):
    folder = tmp_path / "models"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    for force in ([], ["--force"]):
        _refused(["sim", "export", "--out", str(folder), *force], folder, capsys, tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    capsys.readouterr()
    assert main(["sim", "export", "--out", str(empty)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "is a folder" in err and list(empty.iterdir()) == []


# ------------------------------------------------------------------------------------------ sysid demo


def test_demo_refuses_the_users_folder_before_any_work(tmp_path, capsys, monkeypatch):
    mine = tmp_path / "results"
    mine.mkdir()
    (mine / "patch.json").write_text('{"effects": []}')
    (mine / "report.html").write_text("<!doctype html><title>my adadex notes</title>")
    (tmp_path / "thesis.tex").write_text("\\documentclass{article}\n")
    for name in ("load_recording", "compare", "diagnose"):
        _trap(monkeypatch, "adadex.sysid.demo", name)
    _refused(["sysid", "demo", "--threads", "1", "--out", str(mine)], mine, capsys, tmp_path)
    _refused(["sysid", "demo", "--threads", "1", "--out", str(tmp_path / "thesis.tex")], tmp_path / "thesis.tex",
             capsys, tmp_path)


# ------------------------------------------------------------------------------------------ encoder eval


def _cheap_eval(monkeypatch) -> None:
    """The evaluation of 80 objects replaced by a stub: these tests are about the output, not the numbers."""
    import adadex.train.encoder_cli as ec

    per_object = {"cube_050": {"chamfer_cm2": 0.1, "rms_mm": 1.0}}
    monkeypatch.setattr(ec, "evaluate_encoder", lambda model: per_object)
    monkeypatch.setattr(ec, "resampling_floor", lambda points: per_object)
    monkeypatch.setattr(ec, "summarize_evaluation",
                        lambda p: {"train": {"chamfer_cm2": 0.1, "rms_mm": 1.0, "objects": len(p)}})
    monkeypatch.setattr(ec, "plot_reconstructions", lambda model, names, path: Path(path).write_bytes(b"png"))


def test_encoder_eval_guards_its_folder(tmp_path, capsys, monkeypatch):
    ckpt = asset("encoder", "encoder.pt")
    mine = tmp_path / "results"
    mine.mkdir()
    (mine / "eval.json").write_text('{"my": "numbers"}')
    with monkeypatch.context() as m:
        _trap(m, "adadex.train.encoder_cli", "load_encoder")
        _trap(m, "adadex.train.encoder_cli", "evaluate_encoder")
        _refused(["encoder", "eval", str(ckpt), "--out", str(mine)], mine, capsys, tmp_path)

    _cheap_eval(monkeypatch)
    ev = tmp_path / "ev"
    assert main(["encoder", "eval", str(ckpt), "--out", str(ev)]) == 0
    assert main(["encoder", "eval", str(ckpt), "--out", str(ev)]) == 0            # its own earlier output
    assert sorted(p.name for p in ev.iterdir()) == ["eval.json", "reconstructions.png"]
    assert main(["encoder", "eval", str(ckpt), "--out", str(mine), "--force"]) == 0
    assert json.loads((mine / "eval.json").read_text())["checkpoint"] == str(ckpt)
    assert main(["encoder", "eval", str(ckpt), "--out", str(mine)]) == 0          # now an earlier output
