"""Run logs: ``<out>/metrics.csv`` always, TorchRL's CSV logger, and wandb (offline unless the
user sets ``WANDB_MODE``).

``metrics.csv`` has one row per iteration and a column per scalar (a column that appears later is
added to every row); it is rewritten atomically each iteration, and on resume rows past the
checkpoint's iteration are dropped, so the file always matches the checkpoint it continues from.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

from adadex.io import atomic_write_text

METRICS = "metrics.csv"


class RunLog:
    """Scalars of each iteration to ``metrics.csv`` and TorchRL loggers (see the module docstring)."""

    def __init__(self, out, *, name: str, config: dict, wandb: bool = True, keep_until: int | None = None):
        self.path = Path(out) / METRICS
        self.rows: list[dict] = []
        if keep_until is not None and self.path.is_file():
            with self.path.open(newline="") as f:
                self.rows = [r for r in csv.DictReader(f) if int(r["iteration"]) <= keep_until]
        from torchrl.record.loggers.csv import CSVLogger

        self.loggers = [CSVLogger(exp_name=name, log_dir=str(Path(out) / "logs"))]
        if wandb:
            from torchrl.record.loggers.wandb import WandbLogger

            offline = os.environ.get("WANDB_MODE", "offline") in ("offline", "disabled")
            self.loggers.append(WandbLogger(exp_name=name, save_dir=str(out), offline=offline, project="adadex",
                                            config=config))

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
