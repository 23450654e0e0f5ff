"""``adadex sysid excite`` and ``adadex sysid simulate`` guard their ``--out`` (see
``test_writer_guards.py``): a user's file — ``thesis.tex``, or measurements saved with ``np.savez``
that have a recording's keys and shapes — is refused, left byte-identical, before any work; the
command's own earlier output (its marker) is replaced; ``--force`` replaces anything."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adadex.cli import main
from tests.reliability.test_writer_guards import _refused, _trap

EXCITE = ["--joints", "if_dip", "--freqs", "1", "--amps", "1", "--kinds", "sine", "--poses", "loaded",
          "--duration", "1"]


def _user_measurements(path: Path) -> Path:
    """The user's own measurements, saved with ``np.savez``: the keys and shapes of a recording."""
    t = np.arange(61) / 60.0
    np.savez(path, time=t, command=np.zeros((1, 61, 1)), joint_pos=np.full((1, 61, 1), 0.1),
             joint_names=np.array(["if_dip"]))
    return path


# ------------------------------------------------------------------------------------------ sysid excite


@pytest.mark.parametrize("name", ["thesis.tex", "my_measurements.npz"])
def test_excite_refuses_the_users_file(tmp_path, capsys, monkeypatch, name):
    mine = tmp_path / name
    if name.endswith(".npz"):
        _user_measurements(mine)
    else:
        mine.write_text("\\documentclass{article}\n")
    _trap(monkeypatch, "adadex.sysid.excite", "design_excitation")
    _refused(["sysid", "excite", *EXCITE, "--out", str(mine)], mine, capsys, tmp_path)


def test_excite_replaces_its_own_plan_and_force_replaces_anything(tmp_path, capsys):
    from adadex.data.recording import load_recording

    plan = tmp_path / "plan.npz"
    assert main(["sysid", "excite", *EXCITE, "--out", str(plan)]) == 0
    first = plan.read_bytes()
    assert main(["sysid", "excite", *EXCITE, "--amps", "0.5", "--out", str(plan)]) == 0   # its own: replaced
    assert plan.read_bytes() != first
    mine = _user_measurements(tmp_path / "mine.npz")
    assert main(["sysid", "excite", *EXCITE, "--out", str(mine), "--force"]) == 0
    assert load_recording(mine).meta["plan"] is True
    # a simulate output is not a plan
    rec = tmp_path / "rec.npz"
    assert main(["sysid", "simulate", str(plan), "--noise", "0", "--threads", "1", "--out", str(rec)]) == 0
    _refused(["sysid", "excite", *EXCITE, "--out", str(rec)], rec, capsys, tmp_path)


def test_excite_csv_folder_is_guarded(tmp_path, capsys, monkeypatch):
    mine = tmp_path / "plan"
    mine.mkdir()
    (mine / "notes.csv").write_text("t,x\n0,1\n")
    with monkeypatch.context() as m:
        _trap(m, "adadex.sysid.excite", "design_excitation")
        _refused(["sysid", "excite", *EXCITE, "--out", str(tmp_path / "plan.csv")], mine, capsys, tmp_path)
    ours = tmp_path / "ours.csv"
    assert main(["sysid", "excite", *EXCITE, "--out", str(ours)]) == 0
    assert main(["sysid", "excite", *EXCITE, "--out", str(ours)]) == 0
    assert len(list((tmp_path / "ours").glob("*.csv"))) == 1
    assert main(["sysid", "excite", *EXCITE, "--out", str(tmp_path / "plan.csv"), "--force"]) == 0
    assert not (mine / "notes.csv").exists()


# ------------------------------------------------------------------------------------------ sysid simulate


@pytest.fixture
def plan(tmp_path) -> Path:
    p = tmp_path / "plan.npz"
    assert main(["sysid", "excite", *EXCITE, "--out", str(p)]) == 0
    return p


def test_simulate_refuses_the_users_measurements(tmp_path, plan, capsys, monkeypatch):
    """The user's ``measured.npz`` has time/command/joint_pos like a recording: it is still theirs."""
    from adadex.data.recording import load_recording

    measured = tmp_path / "measured.npz"
    np.savez(measured, **load_recording(plan).to_arrays())     # a valid recording, saved by the user
    _trap(monkeypatch, "adadex.sysid.excite", "simulate_recording")
    _refused(["sysid", "simulate", str(plan), "--threads", "1", "--out", str(measured)], measured, capsys, tmp_path)
    _refused(["sysid", "simulate", str(plan), "--threads", "1", "--out", str(plan)], plan, capsys, tmp_path)


def test_simulate_replaces_its_own_recording_and_force_replaces_anything(tmp_path, plan, capsys):
    rec = tmp_path / "rec.npz"
    argv = ["sysid", "simulate", str(plan), "--threads", "1", "--out", str(rec)]
    assert main([*argv, "--seed", "1"]) == 0
    first = rec.read_bytes()
    assert main([*argv, "--seed", "2"]) == 0 and rec.read_bytes() != first
    measured = _user_measurements(tmp_path / "measured.npz")
    assert main(["sysid", "simulate", str(plan), "--threads", "1", "--out", str(measured), "--force", "--seed", "2"]) == 0
    assert measured.read_bytes() == rec.read_bytes()
    assert main(["sysid", "simulate", str(plan), "--threads", "1", "--out", str(measured)]) == 0
    # an earlier output the user has since edited and saved is theirs: refused
    with np.load(rec) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["joint_pos"] = arrays["joint_pos"] + 0.01           # e.g. their calibration offset
    np.savez(rec, **arrays)
    _refused(argv, rec, capsys, tmp_path)


# ------------------------------------------------------------------------------- sysid fit and report


def test_fit_and_report_refuse_a_users_file_that_looks_like_theirs(tmp_path, capsys):
    """A user's JSON with ``effects`` and a user's HTML page that names adadex are not earlier outputs:
    only the marker the command wrote says so. Its own earlier patch is replaced."""
    plan, rec = tmp_path / "plan.npz", tmp_path / "rec.npz"
    assert main(["sysid", "excite", *EXCITE, "--out", str(plan)]) == 0
    assert main(["sysid", "simulate", str(plan), "--noise", "0", "--threads", "1", "--out", str(rec)]) == 0
    notes = tmp_path / "my_effects.json"
    notes.write_text('{"effects": ["my own list"]}\n')
    page = tmp_path / "my_page.html"
    page.write_text("<!DOCTYPE html><title>my notes on adadex</title>\n")
    _refused(["sysid", "fit", str(rec), "--add", "damping:if_dip", "--out", str(notes)], notes, capsys, tmp_path)
    _refused(["sysid", "report", str(rec), "--out", str(page)], page, capsys, tmp_path)
    patch = tmp_path / "patch.json"
    assert main(["sysid", "fit", str(rec), "--add", "damping:if_dip", "--out", str(patch)]) == 0
    assert main(["sysid", "fit", str(rec), "--add", "armature:if_dip", "--out", str(patch)]) == 0   # its own
    assert "armature" in patch.read_text()
