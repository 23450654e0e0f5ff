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
    again = _run(ROOT / "recipes/ablation_table.py", out, cwd=tmp_path)          # its own earlier output: replaced
    assert again.returncode == 0, again.stderr[-2000:]
    (out / "ablation.md").write_text("my notes on the ablation\n")               # the user's now: refused
    refused = _run(ROOT / "recipes/ablation_table.py", out, cwd=tmp_path)
    err = refused.stderr.strip()
    assert refused.returncode == 2 and "\n" not in err and "ablation.md" in err and "--force" in err, err
    assert (out / "ablation.md").read_text() == "my notes on the ablation\n"
    forced = _run(ROOT / "recipes/ablation_table.py", out, "--force", cwd=tmp_path)
    assert forced.returncode == 0 and "| T |" in (out / "ablation.md").read_text()
    (out / "T" / "result.json").write_text('{"summary": {}}')                      # not an evaluation's result
    bad = _run(ROOT / "recipes/ablation_table.py", out, cwd=tmp_path)
    assert bad.returncode == 2 and "T/result.json" in bad.stderr and "config.channels" in bad.stderr, bad.stderr
    empty = _run(ROOT / "recipes/ablation_table.py", tmp_path / "nothing_here", cwd=tmp_path)
    assert empty.returncode == 2 and "no result.json below it" in empty.stderr.strip().splitlines()[-1]


def test_evaluate_recipe_refuses_channels_without_a_modulator(tiny_dataset, tmp_path):
    r = _run(ROOT / "recipes/evaluate.py", f"dataset={tiny_dataset}", "build_preset=null", "channels=R+T",
             f"out={tmp_path}/x", cwd=tmp_path)
    assert r.returncode != 0 and "needs a modulator" in r.stderr
    assert not (tmp_path / "x" / "result.json").exists()


def test_a_recipe_trains_a_policy_it_composed(tiny_dataset, tmp_path):
    """recipes/train_custom_policy.py: the user's critic, TorchRL's KL-penalty loss and a StepCounter,
    trained with the training recipes' keys, without library changes; its checkpoint loads as that class."""
    import importlib.util

    import torch

    out = tmp_path / "custom"
    r = _run(ROOT / "recipes/train_custom_policy.py", f"dataset={tiny_dataset}", "build_preset=null",
             "ppo.total_frames=512", "ppo.frames_per_batch=256", "ppo.minibatch_size=128", "ppo.epochs=1",
             "ppo.update_threads=1", "collector.worlds=8", "collector.env_threads=1", "policy.hidden=[32,32]",
             "eval_max_references=0", "wandb=false", "progress=false", f"out={out}", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    spec = importlib.util.spec_from_file_location("custom_recipe", ROOT / "recipes/train_custom_policy.py")
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    policy = recipe.ReplayResidualOwnCritic.load(out / "custom_policy.pt")
    assert isinstance(policy.critic.module[0], torch.nn.LayerNorm)          # the recipe's own critic
    with (out / "metrics.csv").open() as f:
        header = f.readline().strip().split(",")
    assert "loss_objective" in header and "kl" in header, header             # KLPENPPOLoss's KL term
    assert "clip_fraction" not in header, header                               # ClipPPOLoss's, not written
    r2 = _run(ROOT / "recipes/train_custom_policy.py", f"dataset={tiny_dataset}", "build_preset=null",
              "criticc=1", f"out={tmp_path / 'x'}", cwd=tmp_path)
    assert r2.returncode == 2 and "criticc" in r2.stderr and not (tmp_path / "x").exists()
