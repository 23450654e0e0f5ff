"""The Table 1 pipeline: ``recipes/pipeline.py preset=tiny`` end to end as a user runs it, stage
skipping and resuming, and the pieces it is made of (stage markers, specialist blocks, the
reference subsets of the data-scaling study)."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from adadex.data.reference import ReferenceDataset
from adadex.envs.tracking import TrackingConfig
from adadex.errors import ConfigError
from adadex.eval.table1 import CONDITIONS, METRICS, ROWS, SPLITS
from adadex.modules.tracker import Tracker
from adadex.train.checkpoint import load_checkpoint
from adadex.train.distill import DistillConfig, reference_subset
from adadex.train.config import PPOConfig
from adadex.train.pipeline import PipelineConfig, specialist_blocks
from adadex.train.stages import STAGE, run_stage
from adadex.train.table_so_far import table_so_far

ROOT = Path(__file__).resolve().parents[2]
FIGURES = ("ablation.png", "ablation_object.png", "fig4_object_path.png", "fig5_latent.png", "fig6_scaling.png",
           "fig12_smoothness.png", "channel_usage.png")


def _pipeline(tmp_path, out, tiny_dataset, *extra):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "WANDB_MODE": "offline"}
    return subprocess.run([sys.executable, ROOT / "recipes" / "pipeline.py", "preset=tiny", f"out={out}",
                           f"dataset={tiny_dataset}", *extra],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def tiny_run(tiny_dataset, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pipeline")
    out = tmp / "t1"
    r = _pipeline(tmp, out, tiny_dataset)
    assert r.returncode == 0, r.stderr[-3000:]
    return tmp, out, r


def test_tiny_preset_writes_every_row_metric_and_figure(tiny_run):
    _, out, r = tiny_run
    table = json.loads((out / "table1.json").read_text())
    # each seed says how its tracker compares with replay as soon as both are evaluated, before the modulators train
    for seed in (0, 1):
        line = next(x for x in r.stdout.splitlines() if x.startswith(f"seed {seed}: tracker − replay"))
        assert all(f"{s} {c} " in line for s in SPLITS for c in CONDITIONS), line
        assert r.stdout.index(line) < r.stdout.index(f"seed {seed} modulator"), r.stdout[-3000:]
    assert set(table) == set(SPLITS)
    for split in SPLITS:
        assert set(table[split]) == set(CONDITIONS)
        for condition in CONDITIONS:
            rows = table[split][condition]
            assert set(rows) == set(ROWS)
            for row, entry in rows.items():
                assert entry["seeds"] == 2
                for m in METRICS:
                    assert isinstance(entry[m], float) and entry[m] == entry[m], (split, condition, row, m)
                    lo, hi = entry[f"{m}_ci95"]
                    assert lo <= entry[m] <= hi
                assert 0 <= entry["completion_pct"] <= 100
                # intervals over references from the per-episode results; each row paired with the tracker
                assert entry["ci"] == "bootstrap" and entry["episodes"] > 0
                if row == "tracker":
                    assert "diff_vs_tracker" not in entry
                else:
                    assert set(entry["diff_vs_tracker"]) == set(METRICS) == set(entry["diff_vs_tracker_ci95"])
                    for m in METRICS:
                        lo, hi = entry["diff_vs_tracker_ci95"][m]
                        assert lo <= entry["diff_vs_tracker"][m] <= hi
                        assert entry["diff_vs_tracker"][m] == pytest.approx(entry[m] - rows["tracker"][m], abs=1e-9)
    md = (out / "table1.md").read_text()
    for label in ("kinematic replay", "IL+RL", "+R+O+T", "O only", "unseen object, randomized"):
        assert label in md
    for name in FIGURES:
        data = (out / "figures" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, name
    usage = json.loads((out / "figures" / "channel_usage.json").read_text())
    assert set(usage) == {"R", "RT", "ROT", "O"} and set(usage["O"]) == {"latent"}
    assert set(usage["ROT"]) == {"palm", "grip", "latent", "action"}      # the R rows edit through C by default
    stored = json.loads((out / "seed_0" / "eval" / "channel_usage" / "ROT" / "stage.json").read_text())["result"]
    assert stored == usage["ROT"]                 # a stage: a rerun skips it (below, only the killed stage runs)
    assert "+R+O+T = C+O+T" in md and "object anchor's shift for objects within 10 cm" in md
    # each training stage logged to CSV and wandb (offline), and left a loadable policy
    seed0 = out / "seed_0"
    for stage in ("specialists/spec_0", "specialists/spec_1", "generalist", "baselines/ppo", "baselines/il_rl",
                  "modulators/ROT", "scaling/frac_0.5"):
        assert (seed0 / stage / "metrics.csv").is_file(), stage
        assert (seed0 / stage / "stage.json").is_file(), stage
    assert any((seed0 / "baselines" / "ppo" / "wandb").iterdir())
    # the preset's short episodes reach every stage, and are part of what a stage was run with
    marker = json.loads((seed0 / "eval" / "unseen_trajectory" / "randomized" / "tracker" / "stage.json").read_text())
    assert marker["settings"]["env"] == {"window": 60}
    trained = json.loads((seed0 / "modulators" / "ROT" / "stage.json").read_text())["settings"]
    assert trained["env"] == {"window": 60} and trained["ppo"]["frames_per_batch"] == 256      # the preset's batch
    episodes = marker["result"]["per_episode"]
    assert len(episodes["completion"]) == marker["result"]["summary"]["trajectories"] and "carried" in episodes
    assert "Difference to the tracker" in md
    # below the table: whether O acts, with the O row's difference and how far O can move the tracker
    rho = json.loads((out / "figures" / "smoothness.json").read_text())["tracker"]["mean"]
    assert "**Channel O**" in md and f"ρ = {rho:.3f}" in md and f"{rho * 0.25 * 8:.3f} rad" in md
    assert Tracker.load(seed0 / "generalist" / "tracker.pt").config["residual"] == 0.25
    # the IL+RL baseline trained with the imitation term, vanilla PPO without
    il = (seed0 / "baselines" / "il_rl" / "metrics.csv").read_text().splitlines()[0]
    assert "loss_imitation" in il and "loss_imitation" not in (seed0 / "baselines" / "ppo" / "metrics.csv").read_text()
    # the generalist checked against each teacher on the teacher's own references, paired
    checks = json.loads((out / "generalist_vs_teachers.json").read_text())
    assert set(checks) == {"0", "1"} and len(checks["0"]) == 2            # the tiny preset's 2 specialists
    for c in checks["0"]:
        assert 0 <= c["teacher_completion_pct"] <= 100 and 0 <= c["generalist_completion_pct"] <= 100
        lo, hi = c["generalist_minus_teacher_ci95"]
        assert lo <= c["generalist_minus_teacher"] <= hi
        # and against replay on the same draws: its own stage meets the teacher check's episodes again
        assert c["replay_completion_pct"] + c["teacher_minus_replay"] == pytest.approx(c["teacher_completion_pct"])
        for key in ("teacher_minus_replay", "teacher_minus_replay_object"):
            lo, hi = c[f"{key}_ci95"]
            assert lo <= c[key] <= hi
        assert 0 <= c["replay_object_completion_pct"] <= 100
    assert (seed0 / "eval" / "teachers_vs_replay" / "spec_1" / "stage.json").is_file()
    assert "generalist − teacher" in r.stdout and "teacher − replay" in r.stdout
    assert not any("per_episode" in c for c in checks["0"])              # kept in the stages, pooled below the table
    floor = json.loads((seed0 / "eval" / "teachers_vs_replay" / "spec_0" / "stage.json").read_text())["result"]
    assert len(floor["per_episode"]["teacher_completion"]) == len(floor["per_episode"]["reference"]) > 0
    assert "**The specialists against replay** on their own training references, paired (4 specialists" in md
    # seeds differ: the two generalists are not the same network
    a, b = (Tracker.load(out / f"seed_{s}" / "generalist" / "tracker.pt") for s in (0, 1))
    assert any(not torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters()))


def test_a_second_run_skips_every_stage_and_a_killed_one_resumes(tiny_run, tiny_dataset):
    tmp, out, first = tiny_run
    before = json.loads((out / "table1.json").read_text())
    stage = out / "seed_1" / "modulators" / "RT"
    frames = load_checkpoint(stage)["frames"]
    (stage / "stage.json").unlink()          # as if killed after its last checkpoint
    r = _pipeline(tmp, out, tiny_dataset, "seed_workers=1")     # the first run had the seeds side by side
    assert r.returncode == 0, r.stderr[-3000:]
    ran = [line for line in r.stdout.splitlines() if line.startswith("[run ]")]
    assert ran == ["[run ] seed 1 modulator C+T"], ran
    assert r.stdout.count("[skip]") > 40
    assert load_checkpoint(stage)["frames"] == frames        # continued from the checkpoint, not retrained
    assert json.loads((out / "table1.json").read_text()) == before
    # other settings for finished stages are refused, not silently mixed
    bad = _pipeline(tmp, out, tiny_dataset, "specialist.ppo.total_frames=1024")
    assert bad.returncode == 2 and "run with other settings" in bad.stderr and "Traceback" not in bad.stderr


def test_the_table_so_far_pools_the_seeds_whose_rows_are_in(tiny_run, tiny_dataset, tmp_path):
    _, out, _ = tiny_run
    # a finished run: the same table as the one the pipeline wrote
    full = json.loads((out / "table1.json").read_text())
    copy = tmp_path / "t1"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("table1*", "wandb", "figures"))
    r = _pipeline(tmp_path, copy, tiny_dataset, "table_so_far=true")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "[run ]" not in r.stdout and not (copy / "table1.json").exists()      # nothing trained or evaluated
    so_far = json.loads((copy / "table1_so_far.json").read_text())
    assert so_far["table"] == full
    assert so_far["seeds"] == {f"{s}/{c}": [0, 1] for s in SPLITS for c in CONDITIONS}
    assert "Pooled so far" in (copy / "table1_so_far.md").read_text()
    # seed 1 has evaluated only replay and the tracker on unseen objects, randomized (its chain evaluates
    # them first): those two rows pool both seeds, the others seed 0 alone
    block_dir = copy / "seed_1" / "eval" / "unseen_object" / "randomized"
    for row in ROWS:
        if row not in ("replay", "tracker"):
            shutil.rmtree(block_dir / row)
    table = table_so_far(copy)
    assert table["seeds"]["unseen_object/randomized"] == [0, 1] and table["seeds"]["unseen_trajectory/randomized"] == [0, 1]
    assert table["row_seeds"]["unseen_object/randomized"] == {r: [0, 1] if r in ("replay", "tracker") else [0] for r in ROWS}
    block, whole = table["table"]["unseen_object"]["randomized"], full["unseen_object"]["randomized"]
    assert block["replay"] == whole["replay"] and block["tracker"] == whole["tracker"]
    assert {e["seeds"] for r, e in block.items() if r not in ("replay", "tracker")} == {1}
    assert table["table"]["unseen_trajectory"] == full["unseen_trajectory"]
    seed0 = json.loads((out / "seed_0" / "eval" / "unseen_object" / "randomized" / "ROT" / STAGE).read_text())
    assert block["ROT"]["completion_pct"] == pytest.approx(seed0["result"]["summary"]["completion_pct"], abs=1e-9)
    assert block["ROT"]["episodes"] == seed0["result"]["summary"]["trajectories"]
    assert whole["ROT"]["episodes"] == 2 * block["ROT"]["episodes"]
    assert "unseen_object/randomized: seeds 0, 1 (PPO, IL+RL (DexTrack-style), +R, +R+T, +R+O+T, O only: seed 0)" in \
        (copy / "table1_so_far.md").read_text()
    # a seed whose tracker is not evaluated there yet adds nothing to that block
    shutil.rmtree(block_dir / "tracker")
    assert table_so_far(copy, write=False)["row_seeds"]["unseen_object/randomized"] == {r: [0] for r in ROWS}
    # seeds evaluated with different repeats are not pooled; a folder that is no pipeline's is refused
    stage = copy / "seed_1" / "eval" / "unseen_trajectory" / "nominal" / "tracker" / STAGE
    record = json.loads(stage.read_text())
    record["settings"]["repeats"] += 1
    stage.write_text(json.dumps(record))
    with pytest.raises(ConfigError, match="unseen_trajectory, nominal evaluations were run with different repeats"):
        table_so_far(copy)
    (tmp_path / "mine").mkdir()
    bad = _pipeline(tmp_path, tmp_path / "mine", tiny_dataset, "table_so_far=true")
    assert bad.returncode == 2 and "not a pipeline run's folder" in bad.stderr and "Traceback" not in bad.stderr
    assert list((tmp_path / "mine").iterdir()) == []


def test_bad_settings_are_one_line_errors(tiny_dataset, tmp_path):
    r = _pipeline(tmp_path, tmp_path / "o", tiny_dataset, "seeds=[0,0]")
    assert r.returncode == 2 and "distinct training seeds" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o" / "seed_0").exists()
    with pytest.raises(ConfigError, match="unknown keys"):
        PipelineConfig.from_dict({"out": "o", "specialist_frames": 10})
    for kwargs, message in (
            ({"specialist": {"ppo": {"lr": -1.0}}}, "PipelineConfig.specialist.ppo: PPOConfig.lr"),
            ({"specialist": {"ppo": {"lrr": 1}}}, "PipelineConfig.specialist.ppo: unknown setting 'lrr'"),
            ({"specialist": {"count": 0}}, "PipelineConfig.specialist.count must be"),
            ({"specialist": {"frames": 10}}, "PipelineConfig.specialist: unknown setting 'frames'"),
            ({"baseline": {"imitation_coef": 0.0}}, "PipelineConfig.baseline.imitation_coef"),
            ({"baseline": {"policy": {"anchor_iterations": 0}}}, "PipelineConfig.baseline.policy: PolicyConfig"),
            ({"rollouts": {"criterion": "best"}}, "PipelineConfig.rollouts.criterion"),
            ({"distill": {"batch_size": 0}}, "PipelineConfig.distill.batch_size"),
            ({"evaluation": {"scaling_fractions": (0.0, 1.0)}}, "PipelineConfig.evaluation.scaling_fractions"),
            ({"modulator": {"reference_channel": "X"}}, "PipelineConfig.modulator.reference_channel"),
            ({"modulator": {"modulation": {"persist": True}}}, "PipelineConfig.modulator.modulation: unknown"),
            ({"modulator": {"inputs": "pixels"}}, "PipelineConfig.modulator .*inputs"),
            ({"randomization": {"object_xy": 0.02}}, "PipelineConfig.randomization.*object_xy"),
            ({"randomization": {"object_xy_std": -1.0}}, "PipelineConfig.randomization"),
            ({"env": {"window": 5}}, "PipelineConfig.env: window must be at least"),
            ({"env": {"windows": 60}}, "PipelineConfig.env: unknown setting 'windows'"),
            ({"reward": {"w_prx": 1.0}}, "PipelineConfig.reward: unknown setting 'w_prx'"),
            ({"collector": {"backend": "ray"}}, "PipelineConfig.collector: the pipeline's stages collect locally"),
            ({"collector": {"worlds": 0}}, "PipelineConfig.collector: CollectorConfig.worlds"),
            ({"sim": {"backend": "gpu"}}, "sim.backend"),
            ({"modulator": {"ppo": {"advantage": "group"}}}, "modulator.ppo.advantage=group .*modulator.group_size"),
            ({"specialist": {"ppo": {"advantage": "group"}}, "modulator": {"group_size": 4}},
             "specialist.ppo.advantage=group .*collector.group_size ≥ 2, got 1"),
            ({"modulator": {"group_size": 5}}, "modulator.group_size=5 must divide collector.worlds=64"),
            ({"modulator": {"focus": {"T": ["nope"]}}}, r"PipelineConfig.modulator \(row RT\).*focus.*'nope'")):
        with pytest.raises(ConfigError, match=message):
            PipelineConfig(out="o", **kwargs)
    # the modulators' own groups: only their runs' worlds come in groups
    pc = PipelineConfig(out="o", modulator={"ppo": {"advantage": "group"}, "group_size": 4})
    assert (pc.group_size("modulator"), pc.group_size("specialist")) == (4, 1)


def test_a_group_given_as_a_mapping_changes_only_what_it_names():
    """``specialist={"ppo": {"total_frames": 512}}`` keeps the stage's other settings (the constant
    learning rate, one update thread, the unanchored tracker), not PPOConfig's or PolicyConfig's."""
    from adadex.train.pipeline import SpecialistStage

    pc = PipelineConfig(out="o", specialist={"count": 2, "ppo": {"total_frames": 512}, "policy": {"hidden": [32, 32]}})
    assert pc.specialist.count == 2 and pc.specialist.ppo.total_frames == 512
    assert pc.specialist.ppo.desired_kl == 0.0 and pc.specialist.ppo.update_threads == 1
    assert pc.specialist.policy.anchor == 0.0 and pc.specialist.policy.hidden == (32, 32)
    assert pc == PipelineConfig(out="o", specialist=SpecialistStage(count=2, ppo={"total_frames": 512},
                                                                    policy={"hidden": (32, 32)}))
    # env, reward, randomization and modulation keep only what differs from their classes' defaults
    pc = PipelineConfig(out="o", env={"window": 300, "max_action": 0.2}, reward={"w_prox": 0.5, "w_goal": 2.0},
                        modulator={"modulation": {"persistent": True}})
    assert pc.env == {"max_action": 0.2} and pc.reward == {"w_goal": 2.0} and pc.modulator.modulation == {}
    assert pc.env_config().max_action == 0.2 and pc.env_config().reward.w_goal == 2.0


def _recipe_config(*overrides) -> PipelineConfig:
    """``recipes/pipeline.yaml`` composed with ``overrides``, as the recipe reads it."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from adadex.train import config_store

    config_store.register()
    with initialize_config_dir(config_dir=str(ROOT / "recipes"), version_base="1.3"):
        cfg = OmegaConf.to_container(compose(config_name="pipeline", overrides=list(overrides)), resolve=True)
    assert cfg.pop("force") is False and cfg.pop("table_so_far") is False      # the recipe's own keys
    return PipelineConfig.from_dict(cfg)


def test_the_recipe_lists_only_changes_and_its_node_is_the_dataclass(tmp_path):
    """``pipeline.yaml`` with the small preset is PipelineConfig's defaults but ``out``; the node the
    recipe composes on holds every field of the dataclasses (the modulator group: every
    ModulatorSettings field the pipeline does not set itself)."""
    from adadex.modules.channels import ModulationConfig
    from adadex.train.config import ModulatorSettings
    from adadex.train.pipeline import STAGES
    from adadex.train.schema import defaults_of

    assert _recipe_config("preset=small") == PipelineConfig(out="runs/table1")
    node = PipelineConfig.node()
    assert list(node) == [f.name for f in dataclasses.fields(PipelineConfig)]
    for name, cls in STAGES.items():
        assert set(node[name]) == {f.name for f in dataclasses.fields(cls)}, name
    assert set(node["specialist"]["ppo"]) == {f.name for f in dataclasses.fields(PPOConfig)}
    assert node["specialist"]["ppo"]["total_frames"] == 250_000 and node["baseline"]["ppo"]["total_frames"] == 500_000
    assert set(node["modulator"]["modulation"]) == {f.name for f in dataclasses.fields(ModulationConfig)}
    assert set(node["env"]) == {f.name for f in dataclasses.fields(TrackingConfig)} - {"reward"}
    # learner/paired: the paired learner fits only channels chosen once per episode, and every pipeline row
    # (R, RT, ROT, O) acts every step, so they are not pipeline settings
    settings = {f.name for f in dataclasses.fields(ModulatorSettings)} - {"tracker", "channels", "learner", "paired"}
    assert settings <= set(node["modulator"])
    own = defaults_of(ModulatorSettings)
    # ModulatorSettings' defaults but for Table 1's modulator: C's palm starting at the anchor within 10 cm
    # (the R rows' channel is C), read 4 frames ahead, every channel exploring at 0.03
    chosen = {"init_scale": 0.03, "prior": "anchor", "prior_reach": 0.10}
    assert all(node["modulator"][k] == own[k] for k in settings - {"modulation"} - set(chosen))
    assert {k: node["modulator"][k] for k in chosen} == chosen and node["modulator"]["reference_channel"] == "C"
    assert node["modulator"]["modulation"]["reach_lookahead"] == 4 and node["modulator"]["ppo"]["desired_kl"] == 0.016


def test_a_nested_override_reaches_the_stage_it_names(tiny_dataset, tmp_path):
    """``specialist.ppo.lr=…`` on the recipe's command line trains the specialists with it (and only
    them); the preset's batch settings reach every training stage."""
    from adadex.train.pipeline import Pipeline

    pipe = Pipeline(_recipe_config("preset=tiny", f"out={tmp_path}", "specialist.ppo.lr=1e-4"))
    pipe.ds = ReferenceDataset(tiny_dataset)
    seen = []
    pipe._ppo = lambda tc, label, teacher=None: seen.append(tc) or {"policy": f"p{len(seen)}"}
    pipe.specialists(0, tmp_path / "seed_0")
    pipe.baselines(0, tmp_path / "seed_0", "rollouts")
    specialists, baselines = seen[:2], seen[2:]
    assert len(specialists) == 2 and all(tc.ppo.lr == 1e-4 and tc.ppo.total_frames == 512 for tc in specialists)
    assert all(tc.ppo.lr == PPOConfig().lr for tc in baselines)
    assert all(tc.ppo.frames_per_batch == 256 and tc.env == {"window": 60} and tc.policy.hidden == (32, 32)
               for tc in seen)


def test_an_unknown_nested_key_is_refused_by_the_recipe(tiny_dataset, tmp_path):
    r = _pipeline(tmp_path, tmp_path / "o", tiny_dataset, "specialist.ppo.lrr=1")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "'specialist.ppo.lrr'" in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()


def test_randomization_changes_reach_training_rollouts_and_evaluation(tiny_dataset, tmp_path, monkeypatch):
    """``randomization`` is one setting for the whole chain: the training runs, the teacher rollouts and
    the randomized evaluations all see Table 3 with the change (nominal evaluations none)."""
    import importlib

    evaluate_module = importlib.import_module("adadex.eval.evaluate")   # the module (adadex.eval.evaluate is the function)
    from adadex.train import pipeline as pipeline_module
    from adadex.train import rollouts as rollouts_module

    pipe = pipeline_module.Pipeline(PipelineConfig(out=str(tmp_path), randomization={"object_xy_std": 0.02}))
    pipe.ds = ReferenceDataset(tiny_dataset)
    tc = pipe._train_config(tmp_path / "run", 0, pipe.cfg.specialist.ppo, pipe.cfg.specialist.policy)
    assert tc.randomization_config().object_xy_std == 0.02
    assert tc.randomization_config().object_yaw_std == PipelineConfig(out="o").randomization_config().object_yaw_std
    seen = {}

    def fake_evaluate(policy, ds, **kw):
        seen.setdefault("evaluate", []).append(kw["randomize"])
        return {"summary": {}, "per_reference": []}

    def fake_rollouts(teachers, ds, out, **kw):
        seen["rollouts"] = kw["randomize"]
        return {"episodes_tried": 0, "episodes_kept": 0, "success_pct": 0.0, "frames": 0}

    monkeypatch.setattr(evaluate_module, "evaluate", fake_evaluate)
    monkeypatch.setattr(rollouts_module, "teacher_rollouts", fake_rollouts)
    for condition in ("randomized", "nominal"):
        pipe.evaluate(pipe.policy("replay", {}), "unseen_trajectory", condition, 0, references=[0])
    pipe.rollouts(0, tmp_path / "seed_0", {"t.pt": [0]})
    assert seen["evaluate"][0].object_xy_std == 0.02 and seen["evaluate"][1] is None
    assert seen["rollouts"].object_xy_std == 0.02


def test_table_rows_draw_repeats_and_the_checks_draw_check_repeats(tiny_dataset, tmp_path, monkeypatch):
    """Table 1's randomized rows run ``evaluation.repeats`` episodes per test reference (nominal ones one),
    the teacher check and the data-scaling study ``evaluation.check_repeats``."""
    import importlib

    evaluate_module = importlib.import_module("adadex.eval.evaluate")
    from adadex.train import pipeline as pipeline_module

    pipe = pipeline_module.Pipeline(PipelineConfig(out=str(tmp_path), evaluation={"repeats": 5, "check_repeats": 2}))
    pipe.ds = ReferenceDataset(tiny_dataset)
    counts = []

    def fake_evaluate(policy, ds, **kw):
        counts.append(len(kw["references"]))
        return {"summary": {}, "per_reference": []}

    monkeypatch.setattr(evaluate_module, "evaluate", fake_evaluate)
    for condition in ("randomized", "nominal"):
        pipe.evaluate(pipe.policy("replay", {}), "unseen_trajectory", condition, 0, references=[0, 1])
    pipe.evaluate(pipe.policy("replay", {}), "unseen_trajectory", "randomized", 0, references=[0, 1],
                  repeats=pipe.cfg.evaluation.check_repeats)
    assert counts == [10, 2, 4]
    with pytest.raises(ConfigError, match="check_repeats"):
        PipelineConfig(out=str(tmp_path), evaluation={"check_repeats": 0})


def test_pipeline_trackers_are_unanchored_unless_asked(tiny_dataset, tmp_path):
    """The pipeline trains plain residual trackers (the stages' ``policy`` default), while PolicyConfig,
    which the specialist recipes use, keeps its anchor; ``specialist.policy.anchor`` sets it back, other
    keys keep the default."""
    from adadex.train import pipeline as pipeline_module
    from adadex.train.config import PolicyConfig

    assert PolicyConfig().anchor > 0
    for policy, anchor in (({}, 0.0), ({"hidden": [32, 32]}, 0.0), ({"anchor": 0.05}, 0.05)):
        for stage in ("specialist", "baseline"):
            cfg = PipelineConfig(out=str(tmp_path), **{stage: {"policy": policy}})
            pipe = pipeline_module.Pipeline(cfg)
            pipe.ds = ReferenceDataset(tiny_dataset)
            group = getattr(cfg, stage)
            assert pipe._train_config(tmp_path / "run", 0, group.ppo, group.policy).policy.anchor == anchor


def test_the_anchor_lookahead_keys_a_stage_only_when_set(tiny_dataset, tmp_path, monkeypatch):
    """A training stage's settings name ``policy.anchor_lookahead`` only away from its default (1), so the
    stages of runs from before the setting existed are still theirs; set, it reaches the tracker."""
    from adadex.train import pipeline as pipeline_module

    for policy, stamped in (({}, None), ({"anchor": 0.05, "anchor_lookahead": 4}, 4)):
        cfg = PipelineConfig(out=str(tmp_path), specialist={"policy": policy})
        pipe = pipeline_module.Pipeline(cfg)
        pipe.ds = ReferenceDataset(tiny_dataset)
        seen = []
        monkeypatch.setattr(pipe, "_stage", lambda folder, settings, fn, label: seen.append(settings) or {})
        tc = pipe._train_config(tmp_path / "run", 0, cfg.specialist.ppo, cfg.specialist.policy)
        pipe._ppo(tc, "specialist")
        assert seen[0]["policy"].get("anchor_lookahead") == stamped
        assert tc.policy.tracker().config.get("anchor_lookahead") == stamped


def test_the_modulators_anchor_prior_reaches_the_rows_with_c_and_keys_a_stage_only_when_limited(
        tiny_dataset, tmp_path, monkeypatch):
    """``modulator.prior=anchor`` with ``reference_channel=C``: the rows with C get the prior and its
    reach, the O row neither (it has no palm to shift); ``prior_reach`` names a stage's settings only
    when set, so stages of runs from before the setting existed are still theirs."""
    from adadex.train import pipeline as pipeline_module
    from adadex.train.config import ModulatorSettings

    stage = pipeline_module.ModulatorStage(reference_channel="C", prior="anchor", prior_reach=0.1)
    assert stage.settings("ROT")["prior"] == "anchor" and stage.settings("ROT")["prior_reach"] == 0.1
    assert stage.settings("O")["prior"] is None and stage.settings("O")["prior_reach"] == 0.0
    tracker = str(Tracker(hidden=(16,)).save(tmp_path / "tracker.pt"))
    with pytest.raises(ConfigError, match=r"prior_reach=0.1 \(modulator.prior_reach\) limits the anchor prior"):
        ModulatorSettings(tracker=tracker, channels="C+T", prior_reach=0.1)
    cfg = PipelineConfig(out=str(tmp_path / "out"))
    pipe = pipeline_module.Pipeline(cfg)
    pipe.ds = ReferenceDataset(tiny_dataset)
    seen = []
    monkeypatch.setattr(pipe, "_stage", lambda folder, settings, fn, label: seen.append(settings) or {})
    for reach in (0.0, 0.1):
        m = ModulatorSettings(tracker=tracker, channels="C+T", prior="anchor", prior_reach=reach)
        tc = dataclasses.replace(pipe._train_config(tmp_path / "run", 0, cfg.modulator.ppo, cfg.specialist.policy),
                                 modulator=m)
        pipe._ppo(tc, "modulator")
    assert "prior_reach" not in seen[0]["modulator"] and seen[1]["modulator"]["prior_reach"] == 0.1


def test_sim_backend_reaches_every_training_run_and_keys_the_stages(tiny_dataset, tmp_path):
    """``sim.backend=warp``: every training run's config carries it, and a stage run on one backend is
    not reused on the other (the default backend's stages keep their settings as before)."""
    from adadex.train import pipeline as pipeline_module

    pipe = pipeline_module.Pipeline(PipelineConfig(out=str(tmp_path), sim={"backend": "warp"}))
    pipe.ds = ReferenceDataset(tiny_dataset)
    tc = pipe._train_config(tmp_path / "run", 0, pipe.cfg.specialist.ppo, pipe.cfg.specialist.policy)
    assert pipe.cfg.backend == "warp" and tc.sim.backend == "warp"
    stored = pipeline_module.Pipeline(PipelineConfig(out=str(tmp_path)))
    stored._stage(tmp_path / "st", {"a": 1}, lambda: {"r": 1}, label="st")
    with pytest.raises(ConfigError, match="sim_backend"):
        pipe._stage(tmp_path / "st", {"a": 1}, lambda: {"r": 2}, label="st")
    with pytest.raises(ConfigError, match="sim.backend"):
        PipelineConfig(out=str(tmp_path), sim={"backend": "gpu"})


def test_run_stage_stores_skips_and_refuses_changed_settings(tmp_path):
    calls = []
    fn = lambda: calls.append(1) or {"x": (1, 2)}         # noqa: E731
    assert run_stage(tmp_path / "s", {"a": (1,)}, fn, label="s", log=lambda m: None) == {"x": [1, 2]}
    assert run_stage(tmp_path / "s", {"a": [1]}, fn, label="s", log=lambda m: None) == {"x": [1, 2]}
    assert len(calls) == 1
    with pytest.raises(ConfigError, match=r"differing: \['a'\]"):
        run_stage(tmp_path / "s", {"a": [2]}, fn, label="s", log=lambda m: None)

    def boom():
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        run_stage(tmp_path / "t", {}, boom, label="t", log=lambda m: None)
    assert not (tmp_path / "t" / "stage.json").exists()


def test_specialist_blocks_share_out_whole_groups(tiny_dataset):
    ds = ReferenceDataset(tiny_dataset)
    blocks = specialist_blocks(ds, 2, TrackingConfig().window)
    groups = [{ds.entries[i]["group"] for i in b} for b in blocks]
    assert all(blocks) and not groups[0] & groups[1]
    assert sorted(i for b in blocks for i in b) == [1, 2, 5]
    with pytest.raises(ConfigError, match="semantic groups"):
        specialist_blocks(ds, 3, TrackingConfig().window)


def test_reference_subset_keeps_whole_references():
    n = 60
    rows = TensorDict({"reference": torch.arange(n) // 10, "action": torch.randn(n, 22)}, batch_size=[n])
    buf = TensorDictReplayBuffer(storage=LazyTensorStorage(n))
    buf.extend(rows)
    sub = reference_subset(buf, 0.5, seed=3)
    kept = sub[:]["reference"]
    assert len(sub) == 30 and len(kept.unique()) == 3
    assert torch.equal(reference_subset(buf, 0.5, seed=3)[:]["reference"], kept)
    assert len(reference_subset(buf, 0.01, seed=0)) == 10         # at least one reference
    with pytest.raises(ConfigError, match="fraction"):
        DistillConfig(rollouts="r", out="o", fraction=1.5)


def _alive(pid: int) -> bool:
    try:
        return "\nState:\tZ" not in Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc to find the seed workers")
def test_seed_workers_end_with_a_killed_pipeline(tiny_dataset, tmp_path):
    """kill -9 of a pipeline with the seeds side by side leaves no worker training on (a resumed run would
    otherwise train the same stage alongside an orphan)."""
    import signal
    import time

    env = {**os.environ, "PYTHONPATH": str(ROOT), "WANDB_MODE": "offline"}
    out = tmp_path / "t1"
    p = subprocess.Popen([sys.executable, ROOT / "recipes" / "pipeline.py", "preset=tiny", f"out={out}",
                          f"dataset={tiny_dataset}", "seed_workers=2"], cwd=tmp_path, env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while not all((out / f"seed_{s}" / "specialists").exists() for s in (0, 1)):
        assert p.poll() is None and time.time() < deadline, "the seed workers never started"
        time.sleep(0.5)
    children = [int(c) for c in Path(f"/proc/{p.pid}/task/{p.pid}/children").read_text().split()]
    assert len(children) >= 2, children
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    deadline = time.time() + 30
    while any(_alive(c) for c in children) and time.time() < deadline:
        time.sleep(0.5)
    assert not any(_alive(c) for c in children), [c for c in children if _alive(c)]


def test_a_dataset_built_with_other_settings_is_refused(tiny_dataset, tmp_path):
    """``out/data`` is the pipeline's own build: reused with the settings it was built with, refused
    (not silently mixed) when asked for another preset, seed or grasp."""
    import shutil

    from adadex.train.pipeline import Pipeline

    shutil.copytree(tiny_dataset, tmp_path / "data")
    built = ReferenceDataset(tiny_dataset).info
    planned = bool(built.get("planned_grasp", False))
    same = PipelineConfig(out=str(tmp_path), dataset_preset=built["preset"], dataset_seed=built["seed"],
                          dataset_planned_grasp=planned)
    assert len(Pipeline(same).dataset()) == len(ReferenceDataset(tiny_dataset))
    for other in ({"dataset_planned_grasp": not planned}, {"dataset_seed": built["seed"] + 1}):
        with pytest.raises(ConfigError, match="built with other settings"):
            Pipeline(dataclasses.replace(same, **other)).dataset()


def test_the_teachers_note_pools_every_specialist_or_says_it_cannot():
    """Below Table 1: the specialists against replay, pooled over every specialist of every seed (seeds
    weighted equally); a run with a specialist whose episodes were not kept says so instead of a partial pool."""
    from adadex.train.pipeline import teachers_note

    def floor(refs, teacher, replay):
        return {"reference": refs, "teacher_completion": teacher, "replay_completion": replay,
                "teacher_object_completion": [0.0] * len(refs), "replay_object_completion": [0.0] * len(refs)}

    floors = {"0": [floor([0, 0], [100.0, 60.0], [90.0, 50.0]), floor([1], [80.0], [80.0])],
              "1": [floor([0, 1], [70.0, 70.0], [60.0, 50.0])]}
    note = teachers_note(floors)          # seed 0: +6.7 points an episode on average, seed 1: +15
    assert "(3 specialists, 5 episodes, Table 3): completion +10.8 [" in note and "object completion +0.0" in note
    assert "not pooled" in teachers_note({"0": [floors["0"][0], None]})
