"""Training checkpoints load safely: ``torch.load(weights_only=True)``, so a crafted ``checkpoint.pt``
(then ``resume=true``, or a distillation resuming from it) is refused without running its code, and a
normal save → load round trip, RNG states included, still restores everything exactly."""

from __future__ import annotations

import random
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from adadex.errors import AdadexError
from adadex.train.checkpoint import CHECKPOINT, CheckpointError, load_checkpoint, save_checkpoint, set_rng_state

ROOT = Path(__file__).resolve().parents[2]


class _RunsCode:
    """Unpickling this writes ``marker``: what a crafted checkpoint could do instead."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return exec, (f"open({str(self.marker)!r}, 'w').write('code ran')",)


def _refused(out: Path) -> str:
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(out)
    msg = str(e.value)
    assert isinstance(e.value, AdadexError)
    assert "\n" not in msg and str(out / CHECKPOINT) in msg, msg
    return msg


def test_a_crafted_checkpoint_is_refused_without_running_its_code(tmp_path):
    marker = tmp_path / "pwned"
    out = tmp_path / "run"
    out.mkdir()
    torch.save({"kind": "adadex-train", "module": {}, "payload": _RunsCode(marker)}, out / CHECKPOINT)
    assert "could run code" in _refused(out)
    assert not marker.exists()
    # a damaged one is one line naming the file too
    _save(out)
    data = (out / CHECKPOINT).read_bytes()
    (out / CHECKPOINT).write_bytes(data[: len(data) // 2])
    assert "not a readable training checkpoint" in _refused(out)
    (out / CHECKPOINT).write_bytes(b"garbage")
    _refused(out)


def test_checkpoints_written_before_still_resume_without_opening_a_hole(tmp_path):
    """The earlier format holds numpy's RNG state as ``np.random.get_state()``'s tuple (an array): it
    loads and restores; plain numeric arrays are accepted for it, but an object array (whose items are
    pickles) is not."""
    np.random.seed(11)
    np.random.standard_normal()
    random.seed(12)
    old_rng = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    expected = _draws()
    old = tmp_path / "old"
    old.mkdir()
    torch.save({"kind": "adadex-train", "module": {}, "optimizer": {}, "iteration": 1, "frames": 1, "config": {},
                "rng": old_rng, "extra": {}}, old / CHECKPOINT)
    _draws()
    set_rng_state(load_checkpoint(old)["rng"])
    assert _draws() == expected

    marker = tmp_path / "pwned"
    out = tmp_path / "run"
    out.mkdir()
    evil = np.empty(1, dtype=object)
    evil[0] = _RunsCode(marker)
    torch.save({"kind": "adadex-train", "rng": {"numpy": np.random.get_state()}, "x": evil}, out / CHECKPOINT)
    _refused(out)
    assert not marker.exists()


def _draws() -> tuple:
    return (torch.rand(3).tolist(), np.random.standard_normal(3).tolist(), np.random.randint(0, 1 << 30, 3).tolist(),
            [random.random() for _ in range(3)])


def _save(out: Path, **extra) -> torch.nn.Module:
    torch.manual_seed(1)
    module = torch.nn.Linear(3, 2)
    optim = torch.optim.Adam(module.parameters(), lr=1e-3)
    module(torch.ones(1, 3)).sum().backward()
    optim.step()
    save_checkpoint(out, module=module, optimizer=optim, iteration=7, frames=700,
                    config={"ppo": {"lr": 3e-4, "hidden": (32, 32)}, "seed": 0, "out": str(out), "group": None},
                    extra=extra)
    return module


def test_round_trip_restores_module_optimizer_and_every_rng_exactly(tmp_path):
    torch.manual_seed(3)
    np.random.seed(4)
    random.seed(5)
    np.random.standard_normal()           # leaves numpy's cached Gaussian set: part of its state
    out = tmp_path / "run"
    module = _save(out, obs_moments={"count": 3, "mean": torch.zeros(2, dtype=torch.float64)},
                   generator=torch.Generator().manual_seed(9).get_state())
    # (_save seeded torch itself; what follows the save is what a resumed run must draw again)
    expected = _draws()
    _draws()                              # the run goes on, then is killed …

    blob = load_checkpoint(out)           # … and resumes
    set_rng_state(blob["rng"])
    assert _draws() == expected
    assert blob["iteration"] == 7 and blob["frames"] == 700
    assert blob["config"]["ppo"] == {"lr": 3e-4, "hidden": (32, 32)} and blob["config"]["group"] is None
    fresh = torch.nn.Linear(3, 2)
    fresh.load_state_dict(blob["module"])
    assert all(torch.equal(a, b) for a, b in zip(module.state_dict().values(), fresh.state_dict().values()))
    optim = torch.optim.Adam(fresh.parameters(), lr=1e-3)
    optim.load_state_dict(blob["optimizer"])
    assert optim.state_dict()["state"][0]["step"] == 1
    assert torch.equal(blob["extra"]["obs_moments"]["mean"], torch.zeros(2, dtype=torch.float64))
    # nothing in the file needs more than torch's own weights-only loader: no numpy, no Python objects
    torch.load(out / CHECKPOINT, map_location="cpu", weights_only=True)


def test_every_torch_load_is_weights_only():
    """No ``torch.load`` in the library, the recipes or the benchmarks unpickles arbitrary objects."""
    calls = []
    for folder in ("adadex", "recipes", "benchmarks"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            text = path.read_text(encoding="utf-8")
            for m in re.finditer(r"torch\.load\(", text):
                depth, i = 1, m.end()
                while depth and i < len(text):
                    depth += {"(": 1, ")": -1}.get(text[i], 0)
                    i += 1
                calls.append((f"{path.relative_to(ROOT)}:{text.count(chr(10), 0, m.start()) + 1}",
                              text[m.start():i]))
    assert calls
    unsafe = [where for where, call in calls if not re.search(r"weights_only\s*=\s*True", call)]
    assert unsafe == []
