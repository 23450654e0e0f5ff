"""Teacher rollouts → replay buffer → behaviour cloning, on the tiny dataset (training references
[1, 2, 5]). The teacher is an untrained residual tracker whose correction head is scaled up: it acts
like kinematic replay plus an observation-dependent correction of a few hundredths of a radian, so it
succeeds on some randomized episodes and fails on others, and a fresh student does not already
imitate it."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from adadex.envs.randomization import Randomization
from adadex.errors import AdadexError, ConfigError
from adadex.eval.evaluate import evaluate
from adadex.modules.nets import GaussianHeads, fit_normalizers
from adadex.modules.tracker import Tracker
from adadex.train.checkpoint import save_checkpoint
from adadex.train.config import TrainConfig
from adadex.train.distill import DistillConfig, distill, imitation_loss
from adadex.train.rollouts import (NoSuccessfulRollouts, RolloutsError, load_rollouts, rollouts_info,
                                   specialist_teachers, teacher_action_table, teacher_rollouts)

ROOT = Path(__file__).resolve().parents[2]
REFS = [1, 2, 5]
EPISODES, WORLDS, SEED = 4, 3, 0        # 4 chunks of 3 worlds; chunk k runs with env seed SEED + k


def _teacher(gain: float = 100.0, bias: float = 0.0) -> Tracker:
    torch.manual_seed(0)
    t = Tracker(hidden=(32, 32), residual=0.25)
    head = next(m for m in t.modules() if isinstance(m, GaussianHeads)).heads[0]
    with torch.no_grad():
        head.weight.mul_(gain)
        head.bias[:22] += bias                 # the loc half of the head
    return t


@pytest.fixture(scope="module")
def made(tiny_dataset, tmp_path_factory):
    root = tmp_path_factory.mktemp("distill")
    teacher = _teacher()
    path = teacher.save(root / "spec_g1" / "tracker.pt")
    info = teacher_rollouts({path: REFS}, tiny_dataset, root / "rollouts", episodes_per_reference=EPISODES,
                            seed=SEED, max_worlds=WORLDS, nthread=1, progress=False)
    # the same episodes, independently, through the evaluation loop
    flags, actions = [], []
    for k in range(EPISODES):
        res = evaluate(teacher.actor, tiny_dataset, references=REFS, max_worlds=WORLDS, randomize=Randomization(),
                       seed=SEED + k, nthread=1, progress=False, keep_rollouts=True)
        names = list(res["per_reference"])
        flags.append([res["per_reference"][n]["success_mean_error"] for n in names])
        actions.append(res["rollouts"][0]["action"])
    return {"root": root, "rollouts": root / "rollouts", "info": info, "teacher": teacher, "flags": flags,
            "actions": actions, "dataset": tiny_dataset}


def test_only_successful_trajectories_are_kept(made):
    info, flags = made["info"], made["flags"]
    kept = [(k, w) for k in range(EPISODES) for w in range(WORLDS) if flags[k][w]]
    assert 0 < len(kept) < EPISODES * WORLDS, "the test teacher should succeed on some episodes, not all"
    assert info["episodes_tried"] == EPISODES * len(REFS) and info["episodes_kept"] == len(kept)
    assert info["frames"] == 299 * len(kept)
    for w, r in enumerate(REFS):
        e = info["per_reference"][str(r)]
        assert e["tried"] == EPISODES and e["kept"] == sum(flags[k][w] for k in range(EPISODES))
        assert e["frames"] == 299 * e["kept"] and e["success_pct"] == pytest.approx(100 * e["kept"] / EPISODES)
    assert info["teachers"][0]["name"] == "spec_g1" and info["teachers"][0]["config"]["residual"] == 0.25
    buf = load_rollouts(made["rollouts"])
    data = buf[0:len(buf)]
    assert sorted(set(data["episode"].tolist())) == [k * WORLDS + w for k, w in kept]
    for k, w in kept:                       # every step of a kept episode, with the teacher's actions
        rows = data["episode"] == k * WORLDS + w
        assert set(data["reference"][rows].tolist()) == {REFS[w]}
        order = data["t"][rows].argsort()
        assert data["t"][rows][order].tolist() == list(range(299))
        assert torch.equal(data["action"][rows][order], made["actions"][k][w])


def test_buffer_round_trips_from_disk(made):
    out = made["rollouts"]
    assert rollouts_info(out)["frames"] == made["info"]["frames"]
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".rollouts")]     # no temp folders left
    assert not (out / ".staging").exists()
    a, b = load_rollouts(out), load_rollouts(out)
    assert len(a) == len(b) == made["info"]["frames"]
    x, y = a[0:len(a)], b[0:len(b)]
    for key in ("observation", ("proprio", "joint_target"), ("object", "latent"), "action", "reference", "t",
                "teacher", "episode"):
        assert torch.equal(x[key], y[key]), key
    assert x["observation"].shape[-1] == 273 and x[("proprio", "joint_target")].shape[-1] == 22
    assert a.sample(7)["action"].shape == (7, 22)


def test_teacher_action_table(made):
    buf = load_rollouts(made["rollouts"])
    table, mask = teacher_action_table(buf, num_references=6, window=300)
    assert table.shape == (6, 300, 22) and mask.shape == (6, 300)
    flags = made["flags"]
    for w, r in enumerate(REFS):
        ks = [k for k in range(EPISODES) if flags[k][w]]
        if not ks:
            assert not mask[r].any() and table[r].isnan().all()
            continue
        assert mask[r, :299].all() and not mask[r, 299]
        expect = torch.stack([made["actions"][k][w] for k in ks]).mean(0)
        torch.testing.assert_close(table[r, :299], expect)
    others = [r for r in range(6) if r not in REFS]
    assert not mask[others].any() and table[others].isnan().all()


def _cfg(made, out, **kw) -> DistillConfig:
    base = dict(rollouts=str(made["rollouts"]), out=str(out), steps=40, batch_size=256, lr=2e-3, hidden=(64, 64),
                log_every=10, checkpoint_every=20, wandb=False, progress=False)
    return DistillConfig(**{**base, **kw})


def _weights(path) -> dict:
    return Tracker.load(path).state_dict()


def test_behaviour_cloning_imitates_the_teacher(made, tmp_path):
    res = distill(_cfg(made, tmp_path / "bc", steps=120))
    student = Tracker.load(res["tracker"])
    assert student.config["residual"] == 0.25 and res["steps"] == 120
    with (tmp_path / "bc" / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    first, last = float(rows[0]["probe_loss"]), float(rows[-1]["probe_loss"])
    assert last < 0.3 * first, (first, last)
    # against the teacher itself, on the stored observations: closer than a fresh student
    buf = load_rollouts(made["rollouts"])
    torch.manual_seed(0)
    fresh = Tracker(hidden=(64, 64), residual=0.25)
    fit_normalizers(fresh, buf[0:len(buf)]["observation"])
    assert imitation_loss(student, buf) < 0.3 * imitation_loss(fresh, buf)


def test_resume_continues_exactly_and_same_seed_same_student(made, tmp_path):
    full = distill(_cfg(made, tmp_path / "full"))
    again = distill(_cfg(made, tmp_path / "again"))
    w_full = _weights(full["tracker"])
    assert all(torch.equal(v, _weights(again["tracker"])[k]) for k, v in w_full.items())
    other = distill(_cfg(made, tmp_path / "other", seed=1))
    assert any(not torch.equal(v, _weights(other["tracker"])[k]) for k, v in w_full.items())
    half = distill(_cfg(made, tmp_path / "half", steps=20))
    assert half["steps"] == 20 and not half["resumed"]
    cont = distill(_cfg(made, tmp_path / "half", steps=40, resume=True))
    assert cont["resumed"] and cont["steps"] == 40
    assert all(torch.equal(v, _weights(cont["tracker"])[k]) for k, v in w_full.items())
    with (tmp_path / "half" / "metrics.csv").open(newline="") as f:
        assert [int(r["iteration"]) for r in csv.DictReader(f)] == [0, 10, 20, 30, 40]


def test_bad_inputs_are_adadex_errors(made, tiny_dataset, tmp_path):
    with pytest.raises(RolloutsError, match="no teacher rollouts there"):
        distill(_cfg(made, tmp_path / "x", rollouts=str(tmp_path / "missing")))
    with pytest.raises(AdadexError, match="not a teacher-rollouts folder"):
        distill(_cfg(made, tmp_path / "x", rollouts=str(tmp_path)))
    with pytest.raises(ConfigError, match="success criterion"):
        teacher_rollouts({made["teacher"]: [1]}, tiny_dataset, tmp_path / "r", criterion="completion>=2")
    with pytest.raises(RolloutsError, match="no tracker checkpoint"):
        teacher_rollouts({tmp_path / "nope.pt": [1]}, tiny_dataset, tmp_path / "r")
    with pytest.raises(RolloutsError, match="not usable"):
        teacher_rollouts({made["teacher"]: [99]}, tiny_dataset, tmp_path / "r")
    # a teacher that drives every joint away at full correction: nothing succeeds, nothing is written
    with pytest.raises(NoSuccessfulRollouts, match="nothing to imitate"):
        teacher_rollouts({_teacher(gain=1.0, bias=20.0): [5]}, tiny_dataset, tmp_path / "r", episodes_per_reference=1,
                         nthread=1, progress=False)
    assert not (tmp_path / "r").exists()
    assert issubclass(NoSuccessfulRollouts, AdadexError)


def test_specialist_runs_map_to_their_group_references(made, tiny_dataset, tmp_path):
    runs = tmp_path / "runs"
    for group in (1, 3):
        run = runs / f"specialist_{group}"
        made["teacher"].save(run / "tracker.pt")
        cfg = TrainConfig(dataset="elsewhere", out=str(run), group=group)
        save_checkpoint(run, module=made["teacher"], optimizer=torch.optim.Adam(made["teacher"].parameters()),
                        iteration=1, frames=1, config=cfg.to_dict())
    teachers = specialist_teachers(runs, tiny_dataset)
    assert {Path(k).parent.name: v for k, v in teachers.items()} == {"specialist_1": [1, 2], "specialist_3": [5]}
    with pytest.raises(RolloutsError, match="no specialist run"):
        specialist_teachers(tmp_path / "runs" / "specialist_1", tiny_dataset)


def test_recipes_end_to_end(made, tiny_dataset, tmp_path):
    runs = tmp_path / "runs"
    run = runs / "specialist_3"
    made["teacher"].save(run / "tracker.pt")
    save_checkpoint(run, module=made["teacher"], optimizer=torch.optim.Adam(made["teacher"].parameters()),
                    iteration=1, frames=1, config=TrainConfig(dataset="d", out=str(run), group=3).to_dict())
    py = [sys.executable]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}      # this checkout's adadex, wherever the package is installed
    r = subprocess.run([*py, ROOT / "recipes/teacher_rollouts.py", f"dataset={tiny_dataset}", f"teachers={runs}",
                        f"out={tmp_path}/ro", "episodes_per_reference=3", "max_worlds=3", "env_threads=1",
                        "criterion='completion>=0.1'", "progress=false", "env.window=60"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    info = json.loads((tmp_path / "ro" / "rollouts.json").read_text())
    assert info["teachers"][0]["references"] == [5] and info["episodes_tried"] == 3
    assert info["criterion"] == "completion>=0.1" and 0 < info["frames"] <= 3 * 60      # env.window reached it
    d = subprocess.run([*py, ROOT / "recipes/distill.py", f"rollouts={tmp_path}/ro", f"out={tmp_path}/gen", "steps=5",
                        "batch_size=64", "hidden=[32,32]", "wandb=false", "progress=false"],
                       cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert d.returncode == 0, d.stderr[-2000:]
    assert Tracker.load(tmp_path / "gen" / "tracker.pt").config["residual"] == 0.25
    bad = subprocess.run([*py, ROOT / "recipes/distill.py", f"rollouts={tmp_path}/none", f"out={tmp_path}/g2"],
                         cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert bad.returncode == 2 and "no teacher rollouts there" in bad.stderr and "Traceback" not in bad.stderr


def test_an_anchored_teacher_gives_an_anchored_student(tiny_dataset, tmp_path):
    """The rollouts keep what an object-anchored teacher reads, so its student can be cloned from them."""
    torch.manual_seed(0)
    teacher = Tracker(hidden=(16,), residual=0.25, anchor=0.05)
    path = teacher.save(tmp_path / "spec_a" / "tracker.pt")
    teacher_rollouts({path: REFS[:1]}, tiny_dataset, tmp_path / "rollouts", episodes_per_reference=2, seed=SEED,
                     max_worlds=2, nthread=1, progress=False, criterion="completion>=0.01")
    buf = load_rollouts(tmp_path / "rollouts")
    assert {("object", "start_pose"), ("object", "reference_start")} <= set(buf[0:1].keys(True, True))
    res = distill(DistillConfig(rollouts=str(tmp_path / "rollouts"), out=str(tmp_path / "bc"), steps=4,
                                batch_size=64, hidden=(16,), wandb=False, progress=False))
    assert Tracker.load(res["tracker"]).config["anchor"] == 0.05


def test_teachers_that_anchor_differently_are_refused():
    """A student shares its teachers' feed-forward: one anchor reach for all of them, or none."""
    from adadex.train.distill import teacher_settings

    def info(*reaches):
        return {"teachers": [{"config": Tracker(hidden=(8,), residual=0.25, anchor=0.05, anchor_reach=r).config}
                             for r in reaches]}

    assert teacher_settings(info(0.09, 0.09))["anchor_reach"] == 0.09
    with pytest.raises(RolloutsError, match="anchor_reach"):
        teacher_settings(info(0.09, 0.0))
    old = info(0.0)
    del old["teachers"][0]["config"]["anchor_reach"]                 # a checkpoint saved before it existed
    assert teacher_settings(old)["anchor_reach"] == 0.0


def test_teachers_must_place_the_anchored_palm_alike():
    """Teachers saved before the anchor iterated used one step; a student imitates them with one."""
    from adadex.train.distill import teacher_settings

    def config(iterations, anchor=0.05):
        return Tracker(hidden=(8,), residual=0.25, anchor=anchor, anchor_iterations=iterations).config

    old = config(1)
    del old["anchor_iterations"]
    assert teacher_settings({"teachers": [{"config": old}, {"config": config(1)}]})["anchor_iterations"] == 1
    with pytest.raises(RolloutsError, match="anchor_iterations"):
        teacher_settings({"teachers": [{"config": old}, {"config": config(3)}]})
    unanchored = teacher_settings({"teachers": [{"config": config(1, anchor=0.0)}, {"config": config(3, anchor=0.0)}]})
    assert Tracker(hidden=(8,), **unanchored).config["anchor"] == 0.0        # nothing to place: no conflict
    ahead = Tracker(hidden=(8,), residual=0.25, anchor=0.05, anchor_lookahead=4).config
    assert teacher_settings({"teachers": [{"config": ahead}, {"config": dict(ahead)}]})["anchor_lookahead"] == 4
    with pytest.raises(RolloutsError, match="anchor_lookahead"):          # a teacher saved before it read t+1
        teacher_settings({"teachers": [{"config": ahead}, {"config": config(3)}]})
