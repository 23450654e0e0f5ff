"""The benchmarks and ``adadex encoder train --out`` guard their outputs with the one guard (:mod:`adadex.io`).

Every benchmark writes its JSON result through ``benchmarks/_data.py``'s ``write_result`` (checked first,
right after its arguments are parsed, by ``check_result``): an earlier result of the same benchmark is
replaced, anything else refused with one line and exit code 2 unless ``--force``. ``encoder train --out``
refuses a folder of the user's files before any work. No benchmark is run to completion here.
"""

from __future__ import annotations

import hashlib
import importlib
import json
from pathlib import Path

import numpy as np
import pytest

from adadex.cli import main

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


class _Reached(BaseException):
    """Raised by a trap: the work was reached (BaseException, so no error handler turns it into a code)."""


def _trap(monkeypatch, target: str) -> None:
    def work(*a, **k):
        raise _Reached(target)
    monkeypatch.setattr(target, work)


def _assert_refused(main, argv: list, says: str, capsys) -> None:
    """``main(argv)`` ends with exit code 2 and one line on stderr containing ``says``."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and "\n" not in err and says in err, (argv, err)


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def bench(monkeypatch):
    """Import a benchmark script as its own ``python benchmarks/NAME.py`` run would (``_data`` importable)."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))

    def load(name: str):
        return importlib.import_module(name)
    return load


# ------------------------------------------------------------------------------------------ the helper


def test_write_result_refuses_a_users_file_replaces_its_own(bench, tmp_path, capsys):
    data = bench("_data")
    mine = tmp_path / "my_notes.json"
    mine.write_bytes(b'{"my": "notes"}\n')
    before = mine.read_bytes()
    with pytest.raises(SystemExit) as e:
        data.write_result(mine, {"x": 1}, name="demo", force=False)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("benchmarks/demo.py: error: ") and str(mine) in err and "--force" in err
    assert mine.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["my_notes.json"]
    with pytest.raises(SystemExit):
        data.check_result(mine, name="demo")                         # the check alone refuses the same way
    assert mine.read_bytes() == before

    out = tmp_path / "result.json"                                  # its own earlier result: replaced
    data.write_result(out, {"run": 1}, name="demo", force=False)
    data.write_result(out, {"run": 2}, name="demo", force=False)
    assert json.loads(out.read_text()) == {"run": 2}
    with pytest.raises(SystemExit) as e:                             # another benchmark's result: refused
        data.write_result(out, {"run": 3}, name="other", force=False)
    assert e.value.code == 2 and json.loads(out.read_text()) == {"run": 2}
    out.write_text('{"edited": true}')                              # edited by hand since: refused
    with pytest.raises(SystemExit):
        data.check_result(out, name="demo")

    data.write_result(mine, {"forced": True}, name="demo", force=True)    # --force: replaced, then its own
    assert json.loads(mine.read_text()) == {"forced": True}
    data.write_result(mine, {"again": True}, name="demo", force=False)
    assert json.loads(mine.read_text()) == {"again": True}

    folder = tmp_path / "a_folder"                                  # a folder: never replaced, even forced
    folder.mkdir()
    with pytest.raises(SystemExit) as e:
        data.check_result(folder, name="demo", force=True)
    assert e.value.code == 2 and folder.is_dir()


def test_unmarked_results_in_the_results_folder_are_earlier_results(bench):
    data = bench("_data")
    assert data._unmarked_in_results(data.RESULTS / "demo.json")
    assert not data._unmarked_in_results(Path("/elsewhere/demo.json"))


def test_result_arguments_add_out_and_force_and_check_before_any_work(bench, tmp_path, capsys):
    import argparse

    data = bench("_data")
    mine = tmp_path / "my_notes.json"
    mine.write_text('{"mine": 1}')
    parse = data.result_arguments(argparse.ArgumentParser(), "demo")
    with pytest.raises(SystemExit) as e:
        parse(["--out", str(mine)])
    assert e.value.code == 2 and "--force" in capsys.readouterr().err and mine.read_text() == '{"mine": 1}'
    args = parse(["--out", str(mine), "--force"])
    assert args.out == mine and args.force
    assert parse([]).out == data.RESULTS / "demo.json"


def test_settings_read_k_v_of_a_config_and_refuse_the_rest_in_one_line(bench, capsys):
    from adadex.modules.channels import ModulationConfig

    data = bench("_data")
    got = data.settings("reach_lookahead=4,reach_smooth=true,lambda_palm=0.05", ModulationConfig(), "--modulation", "demo")
    assert got == {"reach_lookahead": 4, "reach_smooth": True, "lambda_palm": 0.05}
    assert data.settings("", ModulationConfig(), "--modulation", "demo") == {}
    for text, says in (("reach_lookahed=4", "'reach_lookahed=4' is not k=v with k a ModulationConfig setting"),
                       ("reach_lookahead", "is not k=v"), ("reach_lookahead=four", "reach_lookahead must be an integer"),
                       ("lambda_palm=wide", "lambda_palm must be a number"), ("reach_smooth=yes", "true or false")):
        with pytest.raises(SystemExit) as e:
            data.settings(text, ModulationConfig(), "--modulation", "demo")
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and "\n" not in err and err.startswith("benchmarks/demo.py: error: --modulation: "), err
        assert says in err, err
    from adadex.envs.randomization import Randomization

    assert data.settings("robot_mass=1:1,object_xy_std=0", Randomization(), "--randomization", "demo") == {
        "robot_mass": (1.0, 1.0), "object_xy_std": 0.0}
    for text, says in (("robot_mass=1", "robot_mass is a range lo:hi of numbers, got '1'"),
                       ("robot_mass=a:b", "is a range lo:hi"), ("effects=x", "effects is not a number, switch or range")):
        with pytest.raises(SystemExit) as e:
            data.settings(text, Randomization(), "--randomization", "demo")
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and "\n" not in err and says in err, err


def test_replay_floor_refuses_bad_feed_forward_and_randomization_before_any_work(bench, tmp_path, monkeypatch, capsys):
    floor = bench("replay_floor")
    _trap(monkeypatch, "adadex.envs.replay.replay_policy")            # its first work
    out = tmp_path / "floor.json"
    for args, says in ((["--feed-forward", "anchor_lookahead=3"], "anchor_lookahead=3) times the object anchor"),
                       (["--feed-forward", "anchor=0.05,anchor_lookahead=3"], "lookahead must be one of the observation's reference frames ahead (1, 2, 4, 12)"),
                       (["--randomization", "object_xy_std=0"], "give --randomize too"),
                       (["--randomize", "--randomization", "object_xy_sd=0"], "not k=v with k a Randomization setting"),
                       (["--repeats", "0"], "--repeats must be ≥ 1"),
                       (["--from-off"], "give --randomize too"),
                       (["--randomize", "--from-off", "--randomization", "robot_mass=1.2:1.1"], "robot_mass"),
                       (["--tracker", str(tmp_path / "t.pt"), "--feed-forward", "anchor=0.05"], "give one"),
                       (["--randomize", "--tracker", str(tmp_path / "absent.pt")], str(tmp_path / "absent.pt")),
                       (["--channel-c", "0,0,0"], "7 numbers (palm x, y, z; index, middle, ring, thumb grip), got 3"),
                       (["--channel-c", "0,0,0,grip,0,0,0"], "is not 7 numbers"),
                       (["--channel-c", "0,0,3,0,0,0,0"], "entry 2 = 3 is outside ±2 (palm)"),
                       (["--channel-c", "0,0,0,0,0,0,1.5"], "entry 6 = 1.5 is outside ±1 (grip)"),
                       (["--channel-c", "0,0,0,1,1,1,1", "--feed-forward", "anchor=0.05"], "give one")):
        _assert_refused(floor.main, ["--dataset", str(tmp_path), "--out", str(out), *args], says, capsys)
    assert not out.exists()


def test_replay_floor_splits_the_paired_difference_by_the_reference_objects_travel(bench):
    floor = bench("replay_floor")
    travel = np.array([0.05, 0.12, 0.16, 0.18, 0.25, 0.30])
    replay = np.full(6, 70.0)
    policy = replay + np.array([-6.0, 0.0, 0.0, 3.0, 9.0, 9.0])      # loses where the object barely moves
    out = floor.by_travel(policy, replay, np.arange(6), travel)
    assert [b["episodes"] for b in out["bins"]] == [1, 1, 2, 2]
    assert [b["diff"] for b in out["bins"]] == pytest.approx([-6.0, 0.0, 1.5, 9.0])
    rules = {r["travel_cm"]: r for r in out["rules"]}
    assert rules[17.0]["fraction"] == pytest.approx(0.5)                     # 0.18, 0.25, 0.30
    assert rules[17.0]["diff"] == pytest.approx(21.0 / 6)                    # the loss at 5 cm left out
    assert rules[15.0]["diff"] == pytest.approx(21.0 / 6) and rules[20.0]["diff"] == pytest.approx(3.0)


def test_specialist_floor_refuses_bad_rows_and_settings_before_any_work(bench, tiny_dataset, tmp_path, monkeypatch,
                                                                       capsys):
    floor = bench("specialist_floor")
    _trap(monkeypatch, "specialist_floor.train_row")                  # its first work
    out = tmp_path / "floor.json"
    base = ["--dataset", str(tiny_dataset), "--out", str(out), "--runs", str(tmp_path / "runs")]
    cases = {"--rows ppo.lr": "'lr' is not k=v with k a PPOConfig setting",
             "--rows optim.lr=1": "section.field=value with section one of",
             "--rows ppo.learning_rate=1e-4": "not k=v with k a PPOConfig setting",
             "--rows reward.w_success=lots": "w_success must be a number",
             "--rows default default": "listed twice",
             "--repeats 0": "--repeats must be ≥ 1",
             "--seeds 0,one": "--seeds",
             "--randomization object_xy_sd=0": "not k=v with k a Randomization setting",
             f"--dataset {tmp_path / 'absent'}": str(tmp_path / "absent")}
    for args, says in cases.items():
        _assert_refused(floor.main, [*base, *args.split()], says, capsys)
    with pytest.raises(_Reached):                                     # good settings: the training starts
        floor.main(["--dataset", str(tiny_dataset), "--out", str(out), "--runs", str(tmp_path / "runs"),
                    "--rows", "default", "collector.group_size=8,ppo.advantage=group,reward.w_success=2"])
    assert not out.exists() and not (tmp_path / "runs").exists()
    assert floor.parse_row("collector.group_size=8,ppo.advantage=group")["collector"] == {"group_size": 8}
    assert floor.tag("policy.anchor=0.05,policy.anchor_reach=0.1") == "policy.anchor-0.05_policy.anchor_reach-0.1"


def test_specialist_floor_refuses_a_users_run_folder_in_one_line(bench, tiny_dataset, tmp_path, capsys):
    """A row's run folder holding the user's files is refused (exit 2, one line), the files untouched."""
    floor = bench("specialist_floor")
    mine = tmp_path / "runs" / "default_s0"
    mine.mkdir(parents=True)
    (mine / "notes.txt").write_text("mine")
    _assert_refused(floor.main, ["--dataset", str(tiny_dataset), "--out", str(tmp_path / "floor.json"),
                                 "--runs", str(tmp_path / "runs"), "--specialists", "2"], "not an adadex output", capsys)
    assert (mine / "notes.txt").read_text() == "mine" and not (tmp_path / "floor.json").exists()


# ------------------------------------------------------------------------------------------ a real benchmark


def test_benchmark_refuses_a_users_file_before_any_work(bench, tmp_path, monkeypatch, capsys):
    sweep = bench("timestep_sweep")
    _trap(monkeypatch, "timestep_sweep.settle_stats")                 # its first work
    mine = tmp_path / "my_notes.json"
    mine.write_text('{"mine": 1}')
    before = _tree(tmp_path)
    with pytest.raises(SystemExit) as e:
        sweep.main(["--hz", "60", "--out", str(mine)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(mine) in err and "--force" in err
    assert _tree(tmp_path) == before
    with pytest.raises(_Reached):                                     # --force: the work starts
        sweep.main(["--hz", "60", "--out", str(mine), "--force"])
    assert _tree(tmp_path) == before


@pytest.mark.parametrize("script", sorted(p.stem for p in BENCHMARKS.glob("*.py") if p.stem != "_data"))
def test_every_benchmark_has_force_and_writes_through_the_helper(script):
    text = (BENCHMARKS / f"{script}.py").read_text(encoding="utf-8")
    checked = '"--force"' in text and "check_result(" in text          # or the helper adds and checks both
    assert (checked or "result_arguments(p, " in text) and "write_result(" in text
    assert "json.dump(" not in text and "atomic_write_text(a.out" not in text


@pytest.mark.parametrize("script", sorted([*(f"benchmarks/{p.name}" for p in BENCHMARKS.glob("*.py")),
                                            *(f"recipes/{p.name}" for p in (BENCHMARKS.parent / "recipes").glob("*.py"))]))
def test_no_command_refuses_with_a_bare_message(script):
    """``raise SystemExit("text")`` exits with code 1, the code of a bug: bad input goes through
    ``refuse`` / ``report_error`` (one line, exit code 2) in every benchmark and recipe."""
    text = (BENCHMARKS.parent / script).read_text(encoding="utf-8")
    assert "raise SystemExit(f\"" not in text and "raise SystemExit(\"" not in text, script


def test_sim2real_seeds_refuses_a_missing_run_in_one_line(bench, tmp_path, capsys):
    seeds = bench("sim2real_seeds")
    out = tmp_path / "pooled.json"
    with pytest.raises(SystemExit) as e:
        seeds.main([str(tmp_path / "no_run"), str(tmp_path / "no_run_either"), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and "\n" not in err and err.startswith("benchmarks/sim2real_seeds.py: error: "), err
    assert "no_run" in err and "sim2real.json" in err and not out.exists()


def test_modulator_benchmarks_refuse_a_malformed_row_before_any_work(bench, tmp_path, monkeypatch, capsys):
    """A row or channel setting whose value is not a number (``prior_reach=abc``), or an unknown option,
    is named in one line with exit code 2 before the dataset is even read."""
    _trap(monkeypatch, "adadex.data.reference.ReferenceDataset")     # their first work
    out = tmp_path / "result.json"
    cases = (("modulator_quality", ["--rows", "C+T:prior=anchor:prior_reach=abc"], "needs a number"),
             ("modulator_quality", ["--rows", "C+T:reach=0.1"], "unknown option 'reach'"),
             ("modulator_usage", ["--init-check", "--channels", "C+T:prior=anchor:prior_reach=abc"], "needs a number"),
             ("modulator_usage", ["--init-check", "--channels", "C+T:reach=0.1"], "unknown option 'reach'"))
    for name, args, says in cases:
        with pytest.raises(SystemExit) as e:
            bench(name).main(["--dataset", str(tmp_path), "--out", str(out), *args])
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and "\n" not in err and err.startswith(f"benchmarks/{name}.py: error: "), err
        assert says in err, (args, err)
    assert not out.exists()


# ------------------------------------------------------------------------------------------ encoder train --out


def test_encoder_train_out_refuses_a_users_folder(tmp_path, monkeypatch, capsys):
    from adadex.io import check_output_dir
    from adadex.train.encoder import TRAINING_KIND, is_training_output

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "encoder.pt").write_text("my weights")
    (mine / "notes.txt").write_text("my notes")
    before = _tree(tmp_path)
    _trap(monkeypatch, "adadex.train.encoder_cli.train_encoder")
    capsys.readouterr()
    assert main(["encoder", "train", "--steps", "1", "--out", str(mine), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(mine) in err and "--force" in err, err
    assert _tree(tmp_path) == before

    a_file = tmp_path / "a_file"                                     # a file: refused even with --force
    a_file.write_text("x")
    assert main(["encoder", "train", "--out", str(a_file), "--force", "--quiet"]) == 2
    assert a_file.read_text() == "x"
    capsys.readouterr()

    with pytest.raises(_Reached):                                     # --force: the work starts
        main(["encoder", "train", "--steps", "1", "--out", str(mine), "--force", "--quiet"])

    earlier = tmp_path / "earlier"                                  # an earlier run (its encoder.json's marker)
    earlier.mkdir()
    (earlier / "encoder.json").write_text(json.dumps({"adadex_output": TRAINING_KIND}))
    (earlier / "encoder.pt").write_text("old weights")
    assert check_output_dir(earlier, TRAINING_KIND, recognize=is_training_output) == earlier
    with pytest.raises(_Reached):
        main(["encoder", "train", "--steps", "1", "--out", str(earlier), "--quiet"])


def test_replay_floor_counts_ended_episodes_per_verb(bench):
    floor = bench("replay_floor")
    table = floor.ended_by_verb([True, False, True, True, False], ["shake", "shake", "lift", "shake", "lift"])
    assert list(table) == ["lift", "shake"]
    assert table["lift"] == {"episodes": 2, "ended_pct": 50.0}
    assert table["shake"]["episodes"] == 3 and table["shake"]["ended_pct"] == pytest.approx(200 / 3)


def test_dataset_replay_pairs_two_builds_by_name_and_refuses_bad_input(bench, tiny_dataset, tmp_path, capsys):
    """A build against itself, randomized: every episode meets the same draws, so every difference is 0."""
    compare = bench("dataset_replay")
    out = tmp_path / "pair.json"
    for args, says in ((["--before", str(tiny_dataset), "--after", str(tmp_path / "absent")], str(tmp_path / "absent")),
                       (["--before", str(tiny_dataset), "--after", str(tiny_dataset), "--repeats", "0"],
                        "--repeats must be ≥ 1")):
        _assert_refused(compare.main, [*args, "--out", str(out)], says, capsys)
    assert not out.exists()
    res = compare.main(["--before", str(tiny_dataset), "--after", str(tiny_dataset), "--randomize", "--repeats", "2",
                        "--seed", "3", "--out", str(out)])
    assert res["references"] >= 2 and len(res["per_episode"]["name"]) == 2 * res["references"]
    assert all(v["diff"] == 0 and v["ci95"] == [0, 0] for v in res["diff"].values()), res["diff"]
    assert res["before_summary"]["completion_pct"] == res["after_summary"]["completion_pct"]
    assert json.loads(out.read_text())["names"] == res["names"]
