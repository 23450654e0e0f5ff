"""The last writers of issue 44: ``evaluate.py`` and ``train_encoder.py`` guard ``out=``; a resume checks
``metrics.csv`` against its checkpoint and continues the same wandb run.

* ``recipes/evaluate.py out=…`` and ``recipes/train_encoder.py out=…`` refuse a folder of the user's own
  files (one line naming it and ``force=true``, exit code 2, the folder byte for byte as it was — not
  even Hydra's ``.hydra/``), and replace their own earlier output;
* a resume over a truncated ``metrics.csv`` keeps the intact rows, drops the damaged one, appends, and
  prints one warning line naming the file, the damaged line and the missing iterations; a file whose
  header is not a metrics header is refused (one line naming it) before anything is written;
* a run started and then resumed logs to one wandb run: the id stored in the run folder at the start is
  passed again (``resume="allow"``) — checked with a stand-in for TorchRL's ``WandbLogger``, no network.
"""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path

import pytest

from adadex.errors import AdadexError
from adadex.train.config import CollectorConfig, PolicyConfig, PPOConfig, TrainConfig
from adadex.train.logs import METRICS, RunLog

from tests.reliability.recipe_runs import refused, run_recipes

ROOT = Path(__file__).resolve().parents[2]



def _user_folder(path: Path, files: dict[str, str]) -> Path:
    path.mkdir(parents=True)
    for name, text in files.items():
        (path / name).write_text(text)
    return path


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def recipes(tiny_dataset, tmp_path_factory):
    """Every recipe case run once, in order, in one interpreter; name → result."""
    tmp = tmp_path_factory.mktemp("writers")
    ev_user = _user_folder(tmp / "report", {"result.json": '{"mine": 1}', "notes.tex": "my notes"})
    enc_user = _user_folder(tmp / "enc_mine", {"encoder.pt": "my weights", "encoder.json": "{}"})
    evaluate, encoder = str(ROOT / "recipes" / "evaluate.py"), str(ROOT / "recipes" / "train_encoder.py")
    ev = [f"dataset={tiny_dataset}", "build_preset=null", "smoothness=false", "max_worlds=8"]
    enc = ["steps=1", "batch_size=1", "points=64", "threads=1"]
    cases = {   # name → (script, args, watched folder); in this order
        "evaluate_user": (evaluate, [*ev, f"out={ev_user}"], ev_user),
        "encoder_user": (encoder, [*enc, f"out={enc_user}"], enc_user),
        "evaluate_first": (evaluate, [*ev, f"out={tmp / 'ev'}"], None),
        "evaluate_again": (evaluate, [*ev, f"out={tmp / 'ev'}", "seed=1"], None),
        "encoder_first": (encoder, [*enc, f"out={tmp / 'enc'}"], None),
        "encoder_again": (encoder, [*enc, f"out={tmp / 'enc'}", "seed=1"], None),
        "evaluate_over_encoder": (evaluate, [*ev, f"out={tmp / 'enc'}"], tmp / "enc"),
        "evaluate_force": (evaluate, [*ev, f"out={ev_user}", "force=true"], None),
    }
    out = run_recipes(cases, tmp, "disabled")
    return {"tmp": tmp, "ev_user": ev_user, "enc_user": enc_user,
            **out}


def test_evaluate_and_train_encoder_refuse_a_user_folder(recipes):
    refused(recipes["evaluate_user"], str(recipes["ev_user"]), "force=true", existed=True)
    refused(recipes["encoder_user"], str(recipes["enc_user"]), "force=true", existed=True)
    assert sorted(p.name for p in recipes["enc_user"].iterdir()) == ["encoder.json", "encoder.pt"]
    # another recipe's output is not theirs either
    refused(recipes["evaluate_over_encoder"], str(recipes["tmp"] / "enc"), "force=true", existed=True)


def test_evaluate_and_train_encoder_replace_their_own_output(recipes):
    tmp = recipes["tmp"]
    for first, again in (("evaluate_first", "evaluate_again"), ("encoder_first", "encoder_again")):
        assert recipes[first]["code"] in (0, None), recipes[first]["err"][-2000:]
        assert recipes[again]["code"] in (0, None), recipes[again]["err"][-2000:]
    assert json.loads((tmp / "ev" / "result.json").read_text())["config"]["seed"] == 1     # the rerun's
    assert json.loads((tmp / "enc" / "encoder.json").read_text())["seed"] == 1
    # force=true writes into the user's folder
    assert recipes["evaluate_force"]["code"] in (0, None), recipes["evaluate_force"]["err"][-2000:]
    assert "summary" in json.loads((recipes["ev_user"] / "result.json").read_text())


# ----------------------------------------------------------------------------------------------
# Resume: metrics.csv and the wandb run


class _FakeWandb:
    """Stands in for TorchRL's WandbLogger: records what it was made with; no wandb, no network."""

    made: list[dict] = []

    def __init__(self, exp_name, offline=False, save_dir=None, id=None, project=None, **kwargs):  # noqa: A002
        self.made.append({"id": id, **kwargs})
        self.experiment = None

    def log_scalar(self, *args, **kwargs):
        pass


def _config(dataset, out, frames: int, **kw) -> TrainConfig:
    return TrainConfig(dataset=str(dataset), out=str(out), wandb=True, progress=False, eval_max_references=0,
                       checkpoint_every=1,
                       ppo=PPOConfig(total_frames=frames, frames_per_batch=256, minibatch_size=128, epochs=1,
                                     update_threads=1),
                       collector=CollectorConfig(worlds=8, env_threads=1), policy=PolicyConfig(hidden=(32, 32)),
                       **kw)


def _rows(out) -> list[dict]:
    with (Path(out) / METRICS).open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def resumed(tiny_dataset, tmp_path_factory):
    """A toy run of 512 frames (2 iterations, a checkpoint each), its metrics.csv cut in the middle of the
    second row, then resumed to 768 frames; the stand-in wandb loggers made, stderr of the resume."""
    import torchrl.record.loggers.wandb as torchrl_wandb

    from adadex.train.ppo import train

    out = tmp_path_factory.mktemp("resume") / "run"
    saved = torchrl_wandb.WandbLogger
    _FakeWandb.made = []
    torchrl_wandb.WandbLogger = _FakeWandb
    try:
        train(_config(tiny_dataset, out, 512))
        whole = (out / METRICS).read_text()
        lines = whole.splitlines(keepends=True)
        assert len(lines) == 3, whole                       # header, iterations 1 and 2
        cut = lines[0] + lines[1] + lines[2][: len(lines[2]) // 3]
        (out / METRICS).write_text(cut)
        import contextlib
        import io

        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            train(_config(tiny_dataset, out, 768, resume=True))
    finally:
        torchrl_wandb.WandbLogger = saved
    return {"out": out, "whole": whole, "made": list(_FakeWandb.made), "err": err.getvalue()}


def test_a_truncated_metrics_csv_on_resume_keeps_the_intact_rows_and_warns(resumed):
    out = resumed["out"]
    warnings = [line for line in resumed["err"].splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1, resumed["err"][-2000:]
    w = warnings[0]
    assert str(out / METRICS) in w and "line 3" in w and "iteration 2" in w, w
    rows = _rows(out)
    assert [r["iteration"] for r in rows] == ["1", "3"]          # the damaged row dropped, not blanked
    original = next(csv.DictReader(resumed["whole"].splitlines()))
    assert {k: rows[0][k] for k in original} == original         # the intact row as it was
    assert all(rows[1][k] != "" for k in original)


def test_start_then_resume_log_to_one_wandb_run(resumed):
    made = resumed["made"]
    assert len(made) == 2, made
    stored = json.loads((resumed["out"] / "wandb_run.json").read_text())["id"]
    assert made[0]["id"] == made[1]["id"] == stored and stored
    assert made[1].get("resume") == "allow"


def test_a_fresh_start_gets_a_new_wandb_id(tmp_path, monkeypatch):
    import torchrl.record.loggers.wandb as torchrl_wandb

    monkeypatch.setattr(torchrl_wandb, "WandbLogger", _FakeWandb)
    _FakeWandb.made = []
    RunLog(tmp_path, name="a", config={}, keep_until=-1)
    RunLog(tmp_path, name="a", config={}, keep_until=3)             # resume: the same
    RunLog(tmp_path, name="a", config={}, keep_until=-1)            # force=true over it: a new run
    ids = [m["id"] for m in _FakeWandb.made]
    assert ids[0] == ids[1] != ids[2]


def _metrics(out: Path, text: str) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    (out / METRICS).write_text(text)
    return out / METRICS


def test_metrics_checks_on_resume(tmp_path, capsys):
    # a whole file: rows past the checkpoint dropped, no warning
    path = _metrics(tmp_path / "whole", "iteration,loss\n1,0.5\n2,0.4\n3,0.3\n")
    log = RunLog(path.parent, name="a", config={}, wandb=False, keep_until=2)
    assert [r["iteration"] for r in log.rows] == ["1", "2"] and "warning" not in capsys.readouterr().err
    # a malformed row in the middle, and rows missing at the end
    path = _metrics(tmp_path / "bad", "iteration,loss\n1,0.5\n2,oops\n3,0.3\n")
    log = RunLog(path.parent, name="a", config={}, wandb=False, keep_until=5)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and str(path) in err[0] and "line 3" in err[0] and "2, 4-5" in err[0], err
    assert [r["iteration"] for r in log.rows] == ["1", "3"]
    # distillation logs every log_every steps: only those are expected
    path = _metrics(tmp_path / "distill", "iteration,loss\n0,1\n50,0.5\n100,0.4\n")
    RunLog(path.parent, name="a", config={"log_every": 50}, wandb=False, keep_until=100)
    assert "warning" not in capsys.readouterr().err
    # a header that is not a metrics header: refused, naming the file; nothing changed
    for text in ("step,loss\n1,0.5\n", "iteration,loss,loss\n1,0.5,0.5\n", ""):
        path = _metrics(tmp_path / f"header{len(text)}", text)
        with pytest.raises(AdadexError, match="not the metrics file") as e:
            RunLog(path.parent, name="a", config={}, wandb=False, keep_until=1)
        assert str(path) in str(e.value) and "\n" not in str(e.value)
        assert path.read_text() == text
