"""The sim-to-real loop (recipes/sim2real.py, adadex/train/sim2real.py): end to end at toy size, the
identification from recordings alone, the gap presets, refusals."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.reliability.recipe_runs import refused, run_recipes

ROOT = Path(__file__).resolve().parents[2]
RECIPE = str(ROOT / "recipes" / "sim2real.py")
GAPS = sorted((ROOT / "assets" / "gaps").glob("*.json"))


def test_gap_presets_load_as_patches():
    from adadex.sim.patch import ModelPatch

    assert len(GAPS) >= 3
    for path in GAPS:
        patch = ModelPatch.load(path)
        assert len(patch.active()) >= 1, path


def test_gap_presets_change_replay(tiny_dataset):
    """Each preset moves kinematic replay's figures (the tiny dataset's references, 40-frame episodes)."""
    from adadex.data.reference import ReferenceDataset
    from adadex.envs.replay import replay_policy
    from adadex.envs.tracking import TrackingConfig, episode_references
    from adadex.eval.evaluate import evaluate
    from adadex.sim.patch import ModelPatch

    ds = ReferenceDataset(tiny_dataset)
    cfg = TrackingConfig(window=40)
    refs = episode_references(ds, None, cfg.window)[:4]

    def figures(patch):
        s = evaluate(replay_policy(), ds, split=None, references=refs, config=cfg, patch=patch, progress=False)["summary"]
        return np.array([s["T_h"], s["R_h"], s["E_finger"], s["T_o"]])

    nominal = figures(None)
    for path in GAPS:
        assert np.abs(figures(ModelPatch.load(path)) - nominal).max() > 1e-3, path


def test_ratio_bootstrap():
    from adadex.train.sim2real import ratio_bootstrap

    rng = np.random.default_rng(0)
    refs = np.repeat(np.arange(30), 2)
    gap = 20 + rng.normal(0, 5, 60)
    r = ratio_bootstrap(0.5 * gap + rng.normal(0, 1, 60), gap, refs)
    assert abs(r["estimate"] - 0.5) < 0.05 and r["ci95"][0] < r["estimate"] < r["ci95"][1]
    assert ratio_bootstrap(gap, -gap, refs) == {"estimate": None, "ci95": None}       # no gap: not defined
    # over seeds: the ratio of the seeds' mean numerator and denominator, references resampled within each
    seeds = np.repeat([0, 1], 60)
    two = ratio_bootstrap(np.concatenate([0.2 * gap, 0.8 * gap]), np.concatenate([gap, gap]), np.tile(refs, 2), seeds)
    assert abs(two["estimate"] - 0.5) < 1e-9 and two["seeds"] == 2 and two["ci95"][0] < 0.5 < two["ci95"][1]


def _run(seed, real="assets/gaps/x.json", recovered=0.5, n_refs=20, repeats=2, oracle=None, gap=0.10):
    """A sim2real.json result of one seed: every row's per-episode completion (fractions), the identified
    modulator recovering ``recovered`` of a ``gap`` (10 points), the oracle ``oracle`` of it (None: no row)."""
    rng = np.random.default_rng(seed)
    refs = np.repeat(np.arange(n_refs), repeats)
    real_c = rng.uniform(0.5, 0.7, refs.size)
    rows = {"tracker_nominal": real_c + gap, "tracker_real": real_c, "modulator_table3_real": real_c + 0.01,
            "modulator_identified_real": real_c + gap * recovered, "finetuned_identified_real": real_c + 0.03}
    if oracle is not None:
        rows["modulator_oracle_real"] = real_c + gap * oracle + rng.normal(0, 0.01, refs.size)
    ep = lambda c: {"reference": refs.tolist(), "repeat": np.tile(np.arange(repeats), n_refs).tolist(),
                    "frames": [299] * refs.size, "completion": c.tolist(), "object_completion": (c / 2).tolist(),
                    "T_o": [0.05] * refs.size}
    return {"real": real, "seed": seed, "recovered_fraction": recovered,
            "per_episode": {k: ep(v) for k, v in rows.items()}}


def test_pool_seeds_pools_paired_rows_over_seeds():
    from adadex.train.sim2real import Sim2RealError, pool_seeds

    pooled = pool_seeds([_run(0, recovered=0.2), _run(1, recovered=0.6), _run(2, recovered=0.7)])
    assert pooled["seeds"] == [0, 1, 2] and pooled["paired_episodes"] == 120
    assert abs(pooled["gap_points"] - 10.0) < 1e-9
    assert abs(pooled["recovered_fraction"] - 0.5) < 1e-9            # (2 + 6 + 7) / 3 points of a 10-point gap
    lo, hi = pooled["recovered_fraction_ci95"]
    assert lo <= 0.5 <= hi
    assert abs(pooled["identified_vs_table3_points"]["estimate"] - 4.0) < 1e-9
    assert abs(pooled["identified_vs_finetuned_points"]["estimate"] - 2.0) < 1e-9
    assert abs(pooled["recovered_fraction_finetuned_identified_real"] - 0.3) < 1e-9
    assert pooled["per_seed_recovered_fraction"] == [0.2, 0.6, 0.7]
    with pytest.raises(Sim2RealError, match="different hidden robots"):
        pool_seeds([_run(0), _run(1, real="assets/gaps/y.json")])
    with pytest.raises(Sim2RealError, match="share a seed"):
        pool_seeds([_run(0), _run(0)])
    with pytest.raises(Sim2RealError, match="at least 2"):
        pool_seeds([_run(0)])


def test_verdict_tells_a_gap_beyond_reach_from_one_the_loop_recovers():
    """The verdict is read off the pooled table: a gap the oracle cannot take back is beyond the channels'
    reach whatever the identification; one the identified modulator takes back past the target is
    recovered; a gap whose interval reaches 0 leaves nothing to recover."""
    from adadex.train.sim2real import format_table, pool_seeds, row_statistics

    def runs(**kw):
        return [_run(s, **kw) for s in (0, 1, 2)]

    assert pool_seeds(runs(recovered=0.8))["verdict"]["kind"] == "recovered"
    assert pool_seeds(runs(recovered=0.3))["verdict"]["kind"] == "partly_recovered"
    beyond = pool_seeds(runs(recovered=0.0, oracle=0.02))["verdict"]
    assert beyond["kind"] == "beyond_reach" and "hidden robot itself" in beyond["text"]
    short = pool_seeds(runs(recovered=0.0, oracle=0.9))["verdict"]
    assert short["kind"] == "not_recovered" and "the channel can" in short["text"]
    assert pool_seeds(runs(recovered=0.0, gap=0.0))["verdict"]["kind"] == "no_gap"
    # one seed's table says it too, and prints it
    one = _run(0, recovered=0.0, oracle=0.0)
    stats = row_statistics({k: {"summary": {"completion_pct": 100 * float(np.mean(v["completion"])),
                                            "object_completion_pct": 0.0, "T_o": 0.05, "success_mean_error_pct": 0.0,
                                            "trajectories": len(v["completion"])}, "per_episode": v}
                            for k, v in one["per_episode"].items()})
    assert stats["verdict"]["kind"] == "beyond_reach"
    assert "verdict: beyond_reach" in format_table(stats)


def test_robots_side_by_side_benchmark(tmp_path, monkeypatch, capsys):
    """benchmarks/sim2real_robots.py: pooled results of two robots → one line each with its verdict, the
    JSON and the figure; a file that is not a pooled result, or a figure of the user's, is refused in one
    line with exit code 2 and nothing written."""
    import importlib

    from adadex.train.sim2real import pool_seeds

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    bench = importlib.import_module("sim2real_robots")
    files = []
    for name, kw in (("soft", dict(recovered=0.8)), ("weak", dict(recovered=0.0, oracle=0.0))):
        f = tmp_path / f"{name}.json"
        f.write_text(json.dumps(pool_seeds([_run(s, real=f"assets/gaps/{name}.json", **kw) for s in (0, 1, 2)])))
        files.append(str(f))
    out = tmp_path / "robots.json"
    res = bench.main([*files, "--out", str(out)])
    assert {n: r["verdict"]["kind"] for n, r in res["robots"].items()} == {"soft": "recovered", "weak": "beyond_reach"}
    assert abs(res["robots"]["soft"]["identified"] - 0.8) < 1e-9 and abs(res["robots"]["weak"]["oracle"]) < 0.05
    assert json.loads(out.read_text())["robots"].keys() == {"soft", "weak"}
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"
    printed = capsys.readouterr().out
    assert "beyond_reach" in printed and "recovered" in printed
    bench.main([*files, "--out", str(out)])                          # its own outputs: replaced
    capsys.readouterr()
    (tmp_path / "notes.json").write_text('{"rows": {}}')
    mine = tmp_path / "mine.png"
    mine.write_bytes(b"my figure")
    for args, says in (([files[0], str(tmp_path / "notes.json")], "not a pooled sim2real result"),
                       ([*files, "--figure", str(mine)], "mine.png")):
        with pytest.raises(SystemExit) as e:
            bench.main([*args, "--out", str(tmp_path / "other.json")])
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and "\n" not in err and says in err, err
    assert mine.read_bytes() == b"my figure" and not (tmp_path / "other.json").exists()


def test_end_to_end_tiny_identifies_from_recordings_alone(tmp_path, tiny_dataset, monkeypatch, capsys):
    """preset=tiny on a copy of a gap preset. Once the recording is made, the copy is deleted: the
    identification, training and evaluation run on without it (evaluation rollouts use the robot as
    it was connected), and the identified patch names the preset's effect, found in the recording."""
    import importlib.util

    from adadex.train import sim2real

    real = tmp_path / "real.json"
    shutil.copyfile(ROOT / "assets" / "gaps" / "arm_delay_wrist_friction.json", real)
    record = sim2real.HiddenRobot.record

    def record_then_disconnect(self, *a, **k):
        path = record(self, *a, **k)
        real.unlink()                            # nothing after the recording can read the hidden patch
        return path

    monkeypatch.setattr(sim2real.HiddenRobot, "record", record_then_disconnect)
    spec = importlib.util.spec_from_file_location("sim2real_recipe", RECIPE)
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    out = tmp_path / "out"
    recipe.main([f"real={real}", f"out={out}", "preset=tiny", f"dataset={tiny_dataset}", "progress=false"])
    assert not real.exists()
    result = json.loads((out / "sim2real.json").read_text())
    for row in ("tracker_nominal", "tracker_real", "modulator_untrained_real", "modulator_table3_real",
                "modulator_identified_real", "finetuned_identified_real"):
        r = result["rows"][row]
        assert 0 <= r["completion_pct"] <= 100 and len(r["completion_pct_ci95"]) == 2
        assert "object_success_pct" in r and "T_o" in r
    assert "vs_tracker_real" in result["rows"]["modulator_identified_real"]
    assert "gap_points" in result and "recovered_fraction" in result and "stage_minutes" in result
    assert (out / "sim2real.png").is_file()
    # the fine-tuned row trained the tracker itself, from replay (its correction heads start at zero)
    from adadex.modules.tracker import Tracker

    tuned = Tracker.load(out / "train" / "finetuned_identified" / "tracker.pt")
    assert any(float(h.weight.detach().abs().max()) > 0 for h in tuned.actor._sampling_parts[0].heads)
    assert "train_finetuned_identified" in result["stage_minutes"]
    assert "recovered_fraction_finetuned_identified_real" in result and "identified_vs_finetuned_points" in result
    from adadex.modules.modulator import Modulator

    trained = Modulator.load(out / "train" / "modulator_identified" / "modulator.pt")
    assert trained.channels == ("K",) and trained.config["context_free"] == ["K"]    # the robot's gains: one value
    gains = result["context_free_actions"]["modulator_identified"]["gain"]
    assert gains == trained.context_free_actions()["gain"] and all(-1 <= g <= 1 for g in gains)
    identified = {e["effect"] for e in result["identified_patch"]["effects"]}
    assert "actuator_delay" in identified, result["identified_patch"]
    assert result["diagnosis"]["verdict"] == "explained"
    printed = capsys.readouterr().out
    assert "tracker_real" in printed and "modulator_identified_real" in printed
    assert f"verdict: {result['verdict']['kind']}" in printed                # the table ends with what it says
    assert "coulomb_friction" not in printed.split("[2/4]")[0]       # the lab's log does not name the hidden effects


def test_refusals(tmp_path):
    """A bad real=, an unrelated out, an unknown key or preset: one line, exit code 2, nothing written."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("x")
    not_patch = tmp_path / "notes.json"
    not_patch.write_text(json.dumps({"a": 1}))
    gap = str(GAPS[0])
    cases = {
        "missing real": (RECIPE, [f"real={tmp_path / 'nope.json'}", f"out={tmp_path / 'o1'}"], tmp_path / "o1"),
        "not a patch": (RECIPE, [f"real={not_patch}", f"out={tmp_path / 'o2'}"], tmp_path / "o2"),
        "no real": (RECIPE, [f"out={tmp_path / 'o3'}"], tmp_path / "o3"),
        "unrelated out": (RECIPE, [f"real={gap}", f"out={mine}"], mine),
        "unknown key": (RECIPE, [f"real={gap}", f"out={tmp_path / 'o4'}", "frame=3"], tmp_path / "o4"),
        "unknown preset": (RECIPE, [f"real={gap}", f"out={tmp_path / 'o5'}", "preset=huge"], tmp_path / "o5"),
        "missing tracker": (RECIPE, [f"real={gap}", f"out={tmp_path / 'o6'}", "tracker=nope.pt"], tmp_path / "o6"),
        "bad backend": (RECIPE, [f"real={gap}", f"out={tmp_path / 'o7'}", "backend=gpu"], tmp_path / "o7"),
        "bad context_free": (RECIPE, [f"real={gap}", f"out={tmp_path / 'o8'}", "context_free=[X]"], tmp_path / "o8"),
        "group without groups": (RECIPE, [f"real={gap}", f"out={tmp_path / 'o9'}", "group_size=1"], tmp_path / "o9"),
    }
    r = run_recipes(cases, ROOT, "offline")
    assert "no such patch file" in refused(r["missing real"], "real=")
    refused(r["not a patch"], "real=", "effects")
    refused(r["no real"], "real=")
    refused(r["unrelated out"], str(mine), "force=true", existed=True)
    refused(r["unknown key"], "frame")
    refused(r["unknown preset"], "preset=huge", "tiny")
    refused(r["missing tracker"], "tracker=nope.pt")
    refused(r["bad backend"], "backend=gpu", "rollout")
    refused(r["bad context_free"], "context_free", "'X'", "R/L")
    refused(r["group without groups"], "group_size=1", "advantage=group")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "notes.json"]      # nothing made


def test_the_learner_settings_reach_the_trained_rows():
    """``decide_every`` and ``desired_kl`` are preset keys (the trained rows' modulator and PPO settings):
    the preset holds them and the rows' PPO config reads the rate; bad values are refused naming the key."""
    from adadex.errors import ConfigError
    from adadex.train.sim2real import _ppo_config, preset

    p = preset("tiny", channels="T", decide_every=12, desired_kl=0.016)
    assert p.decide_every == 12 and _ppo_config(p).desired_kl == 0.016
    assert _ppo_config(preset("tiny")).desired_kl == 0.0              # the constant rate, as before
    with pytest.raises(ConfigError, match="decide_every"):
        preset("tiny", decide_every=0)
    with pytest.raises(ConfigError, match="desired_kl"):
        preset("tiny", desired_kl=-1.0)
