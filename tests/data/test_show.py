"""Tests of the reference figure: a valid PNG, a truthful summary, atomic writes, rendering on/off."""

import os

import matplotlib.image as mpimg
import matplotlib.pyplot as plt
import numpy as np
import pytest

from adadex.data import show
from adadex.data.reference import Reference
from adadex.data.show import plot_reference, rendering_status
from adadex.sim.objects import get_object
from adadex.sim.robot import HOME_QPOS

T = 320


def _reference(frames: int = T) -> Reference:
    s = np.linspace(0.0, 1.0, frames)[:, None]
    far = HOME_QPOS.copy()
    far[:6] += [0.3, 0.3, -0.3, 0.3, 0.3, 0.3]  # arm joints: the palm sweeps ~20 cm
    obj = np.zeros((frames, 7))
    obj[:, 0] = np.linspace(0.40, 0.55, frames)
    obj[:, 1] = np.linspace(-0.10, 0.10, frames)
    obj[:, 2] = get_object("cube_050").half_height
    obj[:, 3] = 1.0
    return Reference.from_joint_positions((1 - s) * HOME_QPOS + s * far, obj, object_name="cube_050",
                                          instruction="push the cube left", group_id=7)


def _no_render(*_args, **_kwargs):
    raise AssertionError("rendering was attempted")


@pytest.fixture(scope="module")
def ref():
    return _reference()


@pytest.fixture(scope="module")
def plain(ref, tmp_path_factory):
    """render=False, with every rendering entry point booby-trapped."""
    folder = tmp_path_factory.mktemp("plain")
    figs = plt.get_fignums()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(show, "_backend", _no_render)
        mp.setattr(show, "_render_frames", _no_render)
        info = plot_reference(ref, str(folder / "sub" / "dir" / "ref.png"), render=False)
    assert plt.get_fignums() == figs  # no figure left registered with pyplot
    return folder, info


def test_png_written_and_valid(plain):
    folder, info = plain
    path = folder / "sub" / "dir" / "ref.png"
    assert info["path"] == str(path) and path.is_file()
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[2] in (3, 4)
    assert 400 <= img.shape[0] <= 1200 and 800 <= img.shape[1] <= 2000
    assert info["size"] == [img.shape[1], img.shape[0]]
    assert img[..., :3].std() > 0.05  # something was drawn


def test_summary_is_truthful_without_rendering(plain, ref):
    _, info = plain
    assert info["rendered"] is False and info["render_frames"] == []
    assert "render=False" in info["render_note"]
    w = ref.window()
    assert info["window"] == [w.start, w.stop] == [0, 300]


def test_no_stray_files(plain):
    folder, _ = plain
    assert sorted(p.name for p in folder.rglob("*") if p.is_file()) == ["ref.png"]


def test_failing_write_leaves_nothing(ref, tmp_path):
    target = tmp_path / "fig.png"
    target.mkdir()
    with pytest.raises(IsADirectoryError):
        plot_reference(ref, target, render=False)
    assert [p.name for p in tmp_path.iterdir()] == ["fig.png"] and not any(target.iterdir())


def test_failing_rename_leaves_nothing(ref, tmp_path, monkeypatch):
    def fail(*_args):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        plot_reference(ref, tmp_path / "fig.png", render=False)
    assert list(tmp_path.iterdir()) == []


def test_bad_arguments(ref, tmp_path):
    with pytest.raises(ValueError, match=r"\.png"):
        plot_reference(ref, tmp_path / "fig.pdf", render=False)
    with pytest.raises(ValueError, match="frames"):
        plot_reference(ref, tmp_path / "fig.png", render=False, frames=0)
    assert list(tmp_path.iterdir()) == []


def test_render_required_but_unavailable(ref, tmp_path, monkeypatch):
    monkeypatch.setattr(show, "_backend", lambda: (None, "offscreen rendering unavailable (no GL here)"))
    monkeypatch.setattr(show, "_render_frames", _no_render)
    with pytest.raises(RuntimeError, match="no GL here"):
        plot_reference(ref, tmp_path / "fig.png", render=True)
    assert list(tmp_path.iterdir()) == []


def test_short_reference_without_window(tmp_path):
    info = plot_reference(_reference(40), tmp_path / "short.png", render=False)
    assert info["window"] == [0, 40] and "only 40 of 300" in info["window_note"]
    assert mpimg.imread(tmp_path / "short.png").shape[0] == info["size"][1]


def test_rendering_when_available(ref, plain, tmp_path):
    available, note = rendering_status()
    if not available:
        assert "unavailable" in note
        with pytest.raises(RuntimeError, match="unavailable"):
            plot_reference(ref, tmp_path / "fig.png", render=True)
        info = plot_reference(ref, tmp_path / "fig.png")  # render=None: draws without the row
        assert info["rendered"] is False and info["render_note"] == note
        return
    info = plot_reference(ref, tmp_path / "fig.png", frames=2)
    assert info["rendered"] is True and info["render_note"] == note
    assert info["render_frames"] == [0, 299]
    img = mpimg.imread(tmp_path / "fig.png")
    assert img.shape[0] > plain[1]["size"][1] + 150  # the row of rendered frames is there
    assert img.shape[1] == plain[1]["size"][0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]
