"""Output folders are written as one unit, and the workbench's answers are never silently wrong."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import adadex.sysid.plots as plots
from adadex.cli import main
from adadex.data.recording import Recording
from adadex.io import OUTPUT_MARKER, output_folder, output_kind
from adadex.sim.patch import ModelPatch
from tests.reliability.test_catalogue import good_recording, user_folder


@pytest.fixture(scope="module")
def nominal_recording(tmp_path_factory) -> Path:
    """A short recording simulated on the nominal model: nothing is missing."""
    from adadex.sysid.excite import design_excitation, simulate_recording

    plan = design_excitation(["if_pip"], freqs=(1.0,), amps=(0.5,), poses=("unloaded",), kinds=("sine",),
                             duration=1.0, rate=60.0)
    path = tmp_path_factory.mktemp("rec") / "nominal.npz"
    simulate_recording(plan, ModelPatch(), noise=2e-4, seed=0, nthread=1).save(path)
    return path


def test_compare_killed_mid_write_leaves_the_previous_output_whole(tmp_path, monkeypatch, capsys):
    rec, out = good_recording(tmp_path), tmp_path / "C"
    assert main(["sysid", "compare", str(rec), "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert set(before) == {"compare.json", "heatmap.png", "overlay_worst.png", OUTPUT_MARKER}
    real, calls = plots.fig_to_png, []

    def dies_on_second_plot(fig):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt       # the user's Ctrl-C, after compare.json and one plot were written
        return real(fig)

    monkeypatch.setattr(plots, "fig_to_png", dies_on_second_plot)
    with pytest.raises(KeyboardInterrupt):
        main(["sysid", "compare", str(rec), "--out", str(out)])
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["C", "rec.npz"]      # no temporary left


def test_stale_temporaries_of_a_killed_run_are_removed_on_the_next_write(tmp_path):
    out = tmp_path / "C"
    stale = tmp_path / f".C.{'ab' * 6}.tmp"
    stale.mkdir()
    (stale / "compare.json").write_text("half")
    (tmp_path / f".C.{'cd' * 6}.old").mkdir()
    with output_folder(out, "compare") as tmp:
        (tmp / "compare.json").write_text("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["C"]
    assert output_kind(out) == "compare"


def test_diagnose_rerun_leaves_no_plot_of_the_previous_run(tmp_path, nominal_recording, capsys):
    out = tmp_path / "D"
    with output_folder(out, "diagnosis") as tmp:        # an earlier run that had hypotheses
        (tmp / "diagnosis.json").write_text("{}")
        (tmp / "hypotheses.png").write_bytes(b"old")
    assert main(["sysid", "diagnose", str(nominal_recording), "--out", str(out), "--threads", "1"]) == 0
    assert json.loads((out / "diagnosis.json").read_text())["verdict"] == "nothing_missing"
    assert not (out / "hypotheses.png").exists()


def test_force_replaces_a_user_folder_and_a_dataset_replaces_a_dataset(tmp_path, tiny_dataset):
    from adadex.data.reference import ReferenceDataset, save_dataset

    refs = list(ReferenceDataset(tiny_dataset))[:1]
    mine = user_folder(tmp_path)
    save_dataset(refs, mine, force=True)
    assert len(ReferenceDataset(mine)) == 1 and not (mine / "thesis.tex").exists()
    save_dataset(refs * 1, mine)                                      # a dataset over a dataset: no force needed
    assert len(ReferenceDataset(mine)) == 1


def test_reading_a_dataset_never_writes(tmp_path, tiny_dataset):
    import shutil

    from adadex.data.reference import ReferenceDataset

    ds_path = Path(shutil.copytree(tiny_dataset, tmp_path / "ds"))
    f = ds_path / "frames" / "object_pose.memmap"
    ds = ReferenceDataset(ds_path)
    fr = ds.frames
    fr["object_pose"][0, 0] = 123.0                      # in memory only: the map is copy-on-write
    assert np.fromfile(f, dtype=np.float32)[0] != 123.0


def test_a_short_recording_is_compared(tmp_path, capsys):
    assert main(["sysid", "compare", str(good_recording(tmp_path, T=10))]) == 0   # 0.15 s


def test_one_sequence_is_diagnosed_on_training_data_and_says_so(tmp_path):
    from adadex.sysid.diagnose import diagnose
    from adadex.sysid.excite import design_excitation, simulate_recording

    plan = design_excitation(["if_pip"], freqs=(1.0,), amps=(0.5,), poses=("unloaded",), kinds=("sine",),
                             duration=1.0, rate=60.0)
    truth = ModelPatch().with_effect("damping", ["if_pip"], [[0.05]])
    rec = simulate_recording(plan, truth, noise=2e-4, seed=0, nthread=1)
    assert rec.num_sequences == 1
    d = diagnose(rec, candidates=("damping", "armature"), joints=["if_pip"], nthread=1, progress=False)
    assert d.train_only_joints == ["if_pip"]
    assert d.hypotheses and all(h["scored_on"] == "train" and h["heldout_error_reduction"] is None
                                for h in d.hypotheses)
    assert all(v is None for h in d.selected for v in h["heldout_error_reduction"])
    assert any("Too few sequences to hold any out" in f for f in d.findings)
    assert not any("of the held-out error" in f for f in d.findings)
    # The diagnosis round-trips, and the report and the plot show it without a held-out figure.
    from adadex.sysid.cli import _diagnosis_plot
    from adadex.sysid.diagnose import Diagnosis
    from adadex.sysid.report import write_report

    d.save(tmp_path)
    back = Diagnosis.load(tmp_path)
    assert back.train_only_joints == ["if_pip"]
    assert _diagnosis_plot(back, tmp_path)
    html = write_report(rec, ModelPatch(), tmp_path / "r.html", diagnosis=back, nthread=1).read_text()
    assert "train only" in html


def test_recording_limits_are_configurable(monkeypatch):
    import adadex.data.recording as recording

    cmd = np.full((1, 5, 1), 0.3)
    monkeypatch.setattr(recording, "SAMPLE_PERIOD_RANGE", (1e-4, 20.0))
    assert Recording(time=np.arange(5) * 16.7, joint_names=("if_pip",), command=cmd, joint_pos=cmd).dt == 16.7
