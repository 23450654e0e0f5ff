"""A training ``out=`` is guarded like every other output (issue 44), and the recipes take no unknown key.

* a folder of the user's own files is refused — one line naming it and ``force=true``, exit code 2,
  nothing written (not even Hydra's ``.hydra/`` or log) — by the PPO recipes, ``distill.py`` and
  ``pipeline.py``;
* a finished run is refused without ``resume=true``; ``resume=true`` without a checkpoint, or with a
  setting that changes the result (``ppo.lr``), is refused naming it; settings that do not
  (``RESUME_NEUTRAL``: threads, a larger ``total_frames`` …) continue; ``force=true`` starts over;
* ``+foo=1``, ``ppo.foo=1``, ``+ppo.foo=1``, ``+preset=tiny`` are refused naming the key and the known ones;
* one error contract: bad input is one line and exit code 2, a bug exit code 1.

The recipes run as ``python recipes/<recipe> …`` would (``__main__``, ``sys.argv``), one after the other
in one interpreter (one import of torch for all), on the tiny dataset; the only training is one toy
run of 512 frames (and its continuation), which the refusals of a finished run need.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import torch

from adadex.errors import AdadexError, ConfigError
from adadex.io import OutputExistsError
from adadex.train.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from adadex.train.config import PPOConfig, TrainConfig

from tests.reliability.recipe_runs import refused, run_recipes

ROOT = Path(__file__).resolve().parents[2]
TINY = ["build_preset=null", "ppo.total_frames=512", "ppo.frames_per_batch=256", "ppo.minibatch_size=128", "ppo.epochs=1",
        "ppo.update_threads=1", "collector.worlds=8", "collector.env_threads=1", "policy.hidden=[32,32]",
        "eval_max_references=0", "wandb=false", "progress=false"]



def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _user_folder(path: Path, files: dict[str, str]) -> Path:
    path.mkdir(parents=True)
    for name, text in files.items():
        (path / name).write_text(text)
    return path


@pytest.fixture(scope="module")
def runs(tiny_dataset, tmp_path_factory):
    """Every case run once (a module fixture: one interpreter, one toy training run); name → result."""
    tmp = tmp_path_factory.mktemp("outs")
    user = _user_folder(tmp / "thesis", {"thesis.tex": "\\documentclass{article}", "metrics.csv": "iteration,mine\n1,42\n"})
    table = _user_folder(tmp / "paper", {"table1.md": "| my own table |\n"})
    distill_user = _user_folder(tmp / "notes", {"notes.txt": "mine"})
    run, empty = tmp / "run", tmp / "empty"
    empty.mkdir()
    ppo = str(ROOT / "recipes" / "train_ppo.py")
    base = [f"dataset={tiny_dataset}", *TINY]
    cases = {   # name → (script, args, watched folder); in this order
        "user_folder": (ppo, [*base, f"out={user}"], user),
        "first_run": (ppo, [*base, f"out={run}"], None),
        "finished_again": (ppo, [*base, f"out={run}"], run),
        "resume_other_lr": (ppo, [*base, f"out={run}", "resume=true", "ppo.lr=1e-3"], run),
        "resume_other_net": (ppo, [*base, f"out={run}", "resume=true", "policy.hidden=[16]", "seed=3"], run),
        "resume_finished": (ppo, [*base, f"out={run}", "resume=true"], run),
        "resume_nothing": (ppo, [*base, f"out={empty}", "resume=true"], empty),
        "plus_foo": (ppo, [*base, f"out={tmp / 'foo'}", "+foo=1"], None),
        "ppo_foo": (ppo, [*base, f"out={tmp / 'foo'}", "ppo.foo=1"], None),
        "plus_ppo_foo": (ppo, [*base, f"out={tmp / 'foo'}", "+ppo.foo=1"], None),
        "plus_preset": (ppo, [*base, f"out={tmp / 'foo'}", "+preset=tiny"], None),
        "continue": (ppo, [*base, f"out={run}", "resume=true", "ppo.total_frames=768", "ppo.update_threads=2",
                           "collector.env_threads=0", "checkpoint_every=3"], None),
        "pipeline_user_folder": (str(ROOT / "recipes" / "pipeline.py"),
                                 ["preset=tiny", f"out={table}", f"dataset={tmp / 'no_dataset'}"], table),
        "distill_user_folder": (str(ROOT / "recipes" / "distill.py"),
                                [f"rollouts={tmp / 'no_rollouts'}", f"out={distill_user}", "wandb=false"], distill_user),
        "distill_resume_nothing": (str(ROOT / "recipes" / "distill.py"),
                                   [f"rollouts={tmp / 'no_rollouts'}", f"out={tmp / 'gen'}", "resume=true",
                                    "wandb=false"], None),
        "force": (ppo, [*base, f"out={run}", "force=true"], None),
    }
    out = run_recipes(cases, tmp, "offline")
    return {"tmp": tmp, "user": user, "table": table, "run": run, "empty": empty, "distill_user": distill_user,
            **out}


def test_a_user_folder_is_refused_by_the_training_recipes_and_the_pipeline(runs):
    for case, folder in (("user_folder", runs["user"]), ("pipeline_user_folder", runs["table"]),
                         ("distill_user_folder", runs["distill_user"])):
        refused(runs[case], str(folder), "force=true")
    # byte for byte the user's, and nothing added (no checkpoint, no .hydra/, no log)
    assert sorted(p.name for p in runs["user"].iterdir()) == ["metrics.csv", "thesis.tex"]
    assert (runs["user"] / "metrics.csv").read_text() == "iteration,mine\n1,42\n"
    assert sorted(p.name for p in runs["table"].iterdir()) == ["table1.md"]
    assert (runs["table"] / "table1.md").read_text() == "| my own table |\n"


def test_a_finished_run_is_refused_without_resume(runs):
    assert runs["first_run"]["code"] == 0, runs["first_run"]["err"][-2000:]
    refused(runs["finished_again"], str(runs["run"]), "finished", "resume=true", "force=true")
    # resume=true on it: nothing to do, the run unchanged (Hydra records the command in .hydra/ and its log)
    r = runs["resume_finished"]
    assert r["code"] == 0, r["err"][-2000:]
    run_files = lambda t: {k: v for k, v in t.items() if not k.startswith(".hydra") and not k.endswith(".log")}  # noqa: E731
    assert run_files(r["before"]) == run_files(r["after"]) and "checkpoint.pt" in r["after"]


def test_resume_without_a_checkpoint_isrefused(runs):
    refused(runs["resume_nothing"], str(runs["empty"]), "no checkpoint")
    assert not any(runs["empty"].iterdir())
    line = [x for x in runs["distill_resume_nothing"]["err"].splitlines() if x.strip()]
    assert runs["distill_resume_nothing"]["code"] == 2 and len(line) == 1 and "no checkpoint" in line[0], line
    assert not (runs["tmp"] / "gen").exists()


def test_resume_with_settings_that_change_the_result_is_refused_naming_them(runs):
    line = refused(runs["resume_other_lr"], "ppo.lr")
    assert "0.0003" in line and "0.001" in line
    line = refused(runs["resume_other_net"], "policy.hidden", "seed")
    assert "ppo.lr" not in line


def test_settings_that_do_not_change_the_result_continue_and_force_starts_over(runs):
    assert runs["continue"]["code"] == 0, runs["continue"]["err"][-2000:]
    assert runs["force"]["code"] == 0, runs["force"]["err"][-2000:]
    # the forced run started over: 512 frames again, not the continued run's 768
    assert load_checkpoint(runs["run"])["frames"] == 512


@pytest.mark.parametrize("case, key, known", [("plus_foo", "'foo'", "known: "), ("ppo_foo", "'ppo.foo'", "known under ppo"),
                                              ("plus_ppo_foo", "'ppo.foo'", "known under ppo"),
                                              ("plus_preset", "'preset'", "known: ")])
def test_unknown_keys_are_refused_naming_them_and_the_known_ones(runs, case, key, known):
    line = refused(runs[case], key, known)
    assert ("lr" if "ppo" in key else "randomization") in line
    assert not (runs["tmp"] / "foo").exists()


# ------------------------------------------------------------------------------------------ the pieces


def _finished(out: Path, **settings) -> TrainConfig:
    cfg = TrainConfig(dataset="data/tiny", out=str(out), ppo=PPOConfig(total_frames=512), **settings)
    net = torch.nn.Linear(2, 2)
    save_checkpoint(out, module=net, optimizer=torch.optim.Adam(net.parameters()), iteration=2, frames=512,
                    config=cfg.to_dict())
    return cfg


def test_check_run_rules(tmp_path):
    """The library's guard, as the trainers call it (the pipeline's stages: ``strict=False``)."""
    from adadex.train.checkpoint import RESUME_NEUTRAL, TRAINING_RUN, check_run

    cfg = _finished(tmp_path / "run")
    d = cfg.to_dict()
    with pytest.raises(OutputExistsError, match="finished training run"):
        check_run(tmp_path / "run", TRAINING_RUN, d, resume=False, strict=False)
    assert check_run(tmp_path / "run", TRAINING_RUN, d, resume=False, force=True) is None
    assert check_run(tmp_path / "run", TRAINING_RUN, d, resume=True)["frames"] == 512
    neutral = TrainConfig(**{**d, "wandb": False, "progress": False, "checkpoint_every": 9,
                             "ppo": {**d["ppo"], "total_frames": 4096, "update_threads": 1},
                             "collector": {**d["collector"], "workers": 2, "env_threads": 0}})
    assert check_run(tmp_path / "run", TRAINING_RUN, neutral.to_dict(), resume=True) is not None
    changed = TrainConfig(**{**d, "dataset": "data/other", "ppo": {**d["ppo"], "lr": 1e-3}})
    with pytest.raises(ConfigError, match=r"ppo\.lr .*dataset|dataset .*ppo\.lr"):
        check_run(tmp_path / "run", TRAINING_RUN, changed.to_dict(), resume=True)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        check_run(tmp_path / "new", TRAINING_RUN, d, resume=True)
    assert check_run(tmp_path / "new", TRAINING_RUN, d, resume=True, strict=False) is None
    mine = _user_folder(tmp_path / "mine", {"thesis.tex": "x"})
    with pytest.raises(OutputExistsError, match="force=true"):
        check_run(mine, TRAINING_RUN, d, resume=False)
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputExistsError, match="not a folder"):
        check_run(tmp_path / "file", TRAINING_RUN, d, resume=False, force=True)
    assert {"ppo.total_frames", "ppo.update_threads", "wandb", "progress"} <= RESUME_NEUTRAL
    assert not {"ppo.lr", "policy.hidden", "seed", "dataset", "modulator.channels"} & RESUME_NEUTRAL


def test_the_trainer_refuses_to_train_over_a_run(tmp_path):
    """``train()`` from Python: a finished run in ``out`` is not silently replaced either."""
    from adadex.train.ppo import PPOTrainer

    cfg = _finished(tmp_path / "run")
    trainer = PPOTrainer.__new__(PPOTrainer)          # only the start-of-run guard: no env, no dataset
    trainer.cfg, trainer.out = cfg, tmp_path / "run"
    with pytest.raises(OutputExistsError, match="resume=true"):
        trainer._resume()


def test_one_error_contract(capsys):
    from adadex.errors import report_error

    assert report_error("recipes/x.py", ConfigError("a.b must be ≥ 0,\ngot -1")) == 2
    assert capsys.readouterr().err == "recipes/x.py: error: a.b must be ≥ 0, got -1\n"
    assert report_error("recipes/x.py", FileNotFoundError("data/x: no such dataset")) == 2
    assert report_error("adadex sim", ZeroDivisionError("division by zero")) == 1
    err = capsys.readouterr().err.splitlines()
    assert err[-1].startswith("adadex sim: internal error (a bug in adadex") and "ZeroDivisionError" in err[-1]
    assert issubclass(OutputExistsError, AdadexError) and issubclass(CheckpointError, AdadexError)


def test_a_setting_added_later_resumes_older_runs_only_at_the_value_they_ran_with():
    """A checkpoint saved before ``modulator.context_free`` existed ran without it (= []): resuming with
    [] goes on, with ["K"] is refused naming it; a setting of unknown past (any other) stays refused."""
    from adadex.train.checkpoint import changed_settings

    old = {"modulator": {"channels": "K", "hidden": [8]}}
    assert changed_settings(old, {"modulator": {"channels": "K", "hidden": [8], "context_free": []}}) == {}
    assert changed_settings(old, {"modulator": {"channels": "K", "hidden": [8], "context_free": ["K"]}}) == {
        "modulator.context_free": ([], ["K"])}
    assert "modulator.history" in changed_settings(old, {"modulator": {"channels": "K", "hidden": [8], "history": 3}})
    # a mapping setting added later (modulator.focus): empty is the run as it was, a focus is a change
    assert changed_settings(old, {"modulator": {"channels": "K", "hidden": [8], "focus": {}}}) == {}
    assert "modulator.focus.K" in changed_settings(old, {"modulator": {"channels": "K", "hidden": [8],
                                                                      "focus": {"K": ["phase"]}}})
    # the anchor's lookahead: runs before it read the reference object at t+1
    tracker = {"policy": {"anchor": 0.05}}
    assert changed_settings(tracker, {"policy": {"anchor": 0.05, "anchor_lookahead": 1}}) == {}
    assert changed_settings(tracker, {"policy": {"anchor": 0.05, "anchor_lookahead": 4}}) == {
        "policy.anchor_lookahead": (1, 4)}
