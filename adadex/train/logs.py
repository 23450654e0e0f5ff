"""Run logs: ``<out>/metrics.csv`` always, TorchRL's CSV logger, and wandb (offline unless the
user sets ``WANDB_MODE``).

``metrics.csv`` has one row per iteration and a column per scalar (a column that appears later is
added to every row); it is rewritten atomically each iteration. On resume (``keep_until``: the
checkpoint's iteration) it is checked against the checkpoint it continues from:

* rows past the checkpoint's iteration are dropped (they were logged after it, and are logged again),
  so the file always matches the checkpoint;
* rows that are damaged (a truncated or otherwise malformed row: a missing or extra field, an iteration
  that is not a whole number, a value that is not a number) are dropped, and iterations up to the
  checkpoint's that have no intact row (a truncated file, a kill between the checkpoint and its row) are
  missing: the run resumes with the intact rows and appends, and says so in **one warning line on
  stderr naming the file, the damaged lines and the missing iterations** — nothing is silently lost or
  blanked. Iterations expected are every ``log_every``-th (``config["log_every"]``, the distillation's;
  1, every iteration, for PPO) from the first up to the checkpoint's;
* a file whose header is not a metrics header (no ``iteration`` column, a column named twice, not a CSV
  file) cannot be continued: refused with one line naming the file and what is wrong
  (:class:`~adadex.errors.AdadexError`, before any training); nothing is written — move it aside or
  delete it to resume.

wandb: a run's id is stored in ``<out>/``:data:`WANDB_RUN` when it starts, and a resume passes the
same id to wandb (``id=…, resume="allow"``), so a run continued after a kill is one wandb run, not one
per start. A fresh start (also ``force=true`` over an earlier run) gets a new id.
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
import secrets
import sys
from pathlib import Path

from adadex.errors import AdadexError
from adadex.io import atomic_write_text

METRICS = "metrics.csv"

#: ``{"id": …}``: the wandb run id of the run in this folder, reused on resume
WANDB_RUN = "wandb_run.json"

_WANDB_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


class MetricsFileError(AdadexError):
    """A ``metrics.csv`` that a resume cannot continue (its header is not a metrics header)."""


def wandb_run_id(out, *, resume: bool) -> str:
    """The wandb run id of the run in ``out``: on ``resume`` the one stored when it started (:data:`WANDB_RUN`);
    otherwise (or when none is stored: a run started before ids were stored) a new one, stored."""
    path = Path(out) / WANDB_RUN
    if resume:
        try:
            found = json.loads(path.read_text(encoding="utf-8")).get("id")
            if isinstance(found, str) and _WANDB_ID.match(found):
                return found
        except (OSError, ValueError, AttributeError):
            pass
    run_id = secrets.token_hex(4)
    atomic_write_text(path, json.dumps({"id": run_id}))
    return run_id


def _spans(numbers: list[int]) -> str:
    """``[1, 2, 3, 7]`` → ``"1-3, 7"``."""
    parts, i = [], 0
    while i < len(numbers):
        j = i
        while j + 1 < len(numbers) and numbers[j + 1] == numbers[j] + 1:
            j += 1
        parts.append(str(numbers[i]) if i == j else f"{numbers[i]}-{numbers[j]}")
        i = j + 1
    return ", ".join(parts)


def _number(value: str) -> bool:
    if value == "":
        return True                      # a column that appeared later: blank in the rows before
    try:
        float(value)
    except ValueError:
        return False
    return True


def read_metrics(path, keep_until: int, *, every: int = 1) -> tuple[list[dict], str | None]:
    """The rows of the metrics file ``path`` to continue from the checkpoint at iteration ``keep_until``
    (see the module docstring), and the warning to print (``None`` when the file is whole). Raises
    :class:`MetricsFileError` for a file that is not a metrics file.

    Args:
        path: the ``metrics.csv`` file.
        keep_until: the checkpoint's iteration: rows past it are dropped.
        every: the iterations between logged rows (default 1), to find missing ones.

    Returns:
        ``(rows, warning)``: the kept rows (dicts of numbers) and the warning line, or None.
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8", errors="replace") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            lines = [(reader.line_num, r) for r in reader]
    except (OSError, csv.Error) as e:
        raise MetricsFileError(f"{path}: cannot be read as the run's metrics ({type(e).__name__}: {e}); move it "
                               f"aside or delete it to resume") from None
    if not header or "iteration" not in header or len(set(header)) != len(header):
        what = ("it is empty" if not header else "its header has no 'iteration' column" if "iteration" not in header
                else "its header names a column twice")
        raise MetricsFileError(f"{path}: not the metrics file this run wrote ({what}); move it aside or delete it "
                               f"to resume (nothing was changed)")
    rows, damaged = [], []
    for line, r in lines:
        if not any(v.strip() for v in r):
            continue                     # a blank line
        if len(r) != len(header) or not all(_number(v) for v in r):
            damaged.append(line)
            continue
        row = dict(zip(header, r))
        try:
            it = int(row["iteration"])
        except ValueError:
            damaged.append(line)
            continue
        if it <= keep_until:
            rows.append(row)
    every = every if isinstance(every, int) and every >= 1 else 1
    present = {int(r["iteration"]) for r in rows}
    missing = [i for i in range(every, keep_until + 1, every) if i not in present]
    if not damaged and not missing:
        return rows, None
    said = []
    if damaged:
        said.append(f"{len(damaged)} damaged row{'s' if len(damaged) > 1 else ''} dropped (line"
                    f"{'s' if len(damaged) > 1 else ''} {_spans(damaged)})")
    if missing:
        said.append(f"no row for iteration{'s' if len(missing) > 1 else ''} {_spans(missing)} of the checkpoint's "
                    f"{keep_until}")
    return rows, (f"warning: {path}: {'; '.join(said)}; resuming with the {len(rows)} intact row"
                  f"{'s' if len(rows) != 1 else ''} and appending (the missing iterations stay missing)")


class RunLog:
    """Scalars of each iteration to ``metrics.csv`` and TorchRL loggers (see the module docstring).

    ``keep_until``: the checkpoint's iteration on resume (``metrics.csv`` is checked against it: rows past it
    dropped; damaged rows and missing iterations reported in one warning line, the intact rows kept; a file
    that is not a metrics file refused with :class:`MetricsFileError`), ``None`` or negative for a fresh run
    (the file is started anew, and wandb gets a new run id; a resume reuses the stored one).

    Args:
        out: the run folder (``metrics.csv``, ``logs/`` and wandb's files go there).
        name: the experiment name in the loggers.
        config: the run's settings (logged to wandb; its ``log_every`` tells :func:`read_metrics`
            the rows' spacing).
        wandb: also log to wandb (default True; offline unless ``WANDB_MODE`` says otherwise).
        keep_until: the checkpoint's iteration when resuming (above), or None.
    """

    def __init__(self, out, *, name: str, config: dict, wandb: bool = True, keep_until: int | None = None):
        self.path = Path(out) / METRICS
        self.rows: list[dict] = []
        resume = keep_until is not None and keep_until >= 0
        if resume and self.path.is_file():
            every = config.get("log_every", 1) if isinstance(config, dict) else 1
            self.rows, warning = read_metrics(self.path, keep_until, every=every)
            if warning:
                print(warning, file=sys.stderr)
        from torchrl.record.loggers.csv import CSVLogger

        self.loggers = [CSVLogger(exp_name=name, log_dir=str(Path(out) / "logs"))]
        if wandb:
            from torchrl.record.loggers.wandb import WandbLogger

            offline = os.environ.get("WANDB_MODE", "offline") in ("offline", "disabled")
            self.wandb_id = wandb_run_id(out, resume=resume)
            self.loggers.append(WandbLogger(exp_name=name, save_dir=str(out), offline=offline, project="adadex",
                                            config=config, id=self.wandb_id, resume="allow"))

    def log(self, iteration: int, scalars: dict) -> None:
        row = {"iteration": iteration, **{k: float(v) for k, v in scalars.items()}}
        self.rows.append(row)
        for lg in self.loggers:
            for k, v in row.items():
                if k != "iteration":
                    lg.log_scalar(k, v, step=iteration)
        columns = list(dict.fromkeys(k for r in self.rows for k in r))
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=columns, restval="")
        w.writeheader()
        w.writerows(self.rows)
        atomic_write_text(self.path, buf.getvalue())

    def close(self) -> None:
        for lg in self.loggers:
            exp = getattr(lg, "experiment", None)
            if exp is not None and hasattr(exp, "finish"):
                exp.finish()
