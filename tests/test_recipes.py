"""The Hydra recipes run end to end on the tiny dataset (as subprocesses, as a user runs them)."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(*args, cwd):
    return subprocess.run([sys.executable, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=600)


def test_evaluate_recipe_ablation_and_table(tiny_dataset, tmp_path):
    out = tmp_path / "runs"
    r = _run(ROOT / "recipes/evaluate.py", "-m", f"dataset={tiny_dataset}", "build_preset=null", "part=train",
             "channels=none,T", "modulator=untrained", "max_worlds=4", f"out={out}/${{channels}}",
             f"hydra.sweep.dir={tmp_path}/multirun", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    results = {c: json.loads((out / c / "result.json").read_text()) for c in ("none", "T")}
    for c, res in results.items():
        assert res["config"]["channels"] == c
        assert res["summary"]["trajectories"] == res["references"] == len(res["per_reference"]) > 0
    t = _run(ROOT / "recipes/ablation_table.py", out, cwd=tmp_path)
    assert t.returncode == 0, t.stderr[-2000:]
    assert "| none |" in t.stdout and "| T |" in t.stdout
    assert (out / "ablation.png").read_bytes()[:4] == b"\x89PNG"


def test_evaluate_recipe_refuses_channels_without_a_modulator(tiny_dataset, tmp_path):
    r = _run(ROOT / "recipes/evaluate.py", f"dataset={tiny_dataset}", "build_preset=null", "channels=R+T",
             f"out={tmp_path}/x", cwd=tmp_path)
    assert r.returncode != 0 and "needs a modulator" in r.stderr
    assert not (tmp_path / "x" / "result.json").exists()
