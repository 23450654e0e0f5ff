"""The pipeline's stage runner: a stage's result stored once with its settings (``stage.json``), reused
when asked again with the same settings and refused with others, and chains of stages run side by side
in processes that end with their parent.

>>> import tempfile, pathlib
>>> folder = pathlib.Path(tempfile.mkdtemp()) / "stage"
>>> run_stage(folder, {"frames": 10}, lambda: {"score": 1.5}, label="demo", log=lambda m: None)
{'score': 1.5}
>>> run_stage(folder, {"frames": 10}, lambda: 1 / 0, label="demo", log=print)    # done: not run again
[skip] demo: done (...)
{'score': 1.5}
"""

from __future__ import annotations

import json
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from adadex.errors import ConfigError
from adadex.io import atomic_write_text

#: the file a finished stage leaves in its folder: its label, settings, result and wall time
STAGE = "stage.json"
#: the output kind of the pipeline's ``out`` (its marker, :mod:`adadex.io`)
PIPELINE_RUN = "table1 pipeline"


def earlier_pipeline(out: Path) -> bool:
    """An ``out`` the pipeline wrote before it was marked: the ``stage.json`` of a stage under ``seed_<s>/``."""
    return any(True for pattern in ("seed_*/*/" + STAGE, "seed_*/*/*/" + STAGE) for _ in Path(out).glob(pattern))


def _plain(x):
    """JSON round trip: tuples become lists, so settings compare equal to their stored form."""
    return json.loads(json.dumps(x, default=str))


def run_stage(folder: Path, settings: dict, fn, *, label: str, log=print) -> dict:
    """``fn()`` once: its result is stored with ``settings`` in ``folder/stage.json``; a later call with
    the same settings returns it without running, one with other settings is refused."""
    marker = folder / STAGE
    settings = _plain(settings)
    if marker.is_file():
        done = json.loads(marker.read_text(encoding="utf-8"))
        if done.get("settings") != settings:
            changed = sorted(k for k in set(settings) | set(done.get("settings", {}))
                             if settings.get(k) != done.get("settings", {}).get(k))
            raise ConfigError(f"{folder}: this stage was run with other settings (differing: {changed}); "
                              f"use a new out= or remove {folder}")
        log(f"[skip] {label}: done ({folder})")
        return done["result"]
    log(f"[run ] {label}")
    t0 = time.perf_counter()
    result = _plain(fn())
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(marker, json.dumps({"stage": label, "settings": settings, "result": result,
                                          "wall_s": time.perf_counter() - t0}, indent=1))
    return result


def run_in_processes(fn: Callable, args: Sequence, workers: int) -> list:
    """``[fn(a) for a in args]``, in ``workers`` spawned processes when ``workers`` > 1 (``fn`` and each
    argument picklable); a process ends when this one does, so a run resumed later never trains a stage
    alongside an orphan writing into the same folder."""
    if workers <= 1:
        return [fn(a) for a in args]
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_die_with_parent, initargs=(os.getpid(),)) as pool:
        return list(pool.map(fn, args))


def _die_with_parent(parent: int) -> None:
    """A worker ends when its parent does (killed with ``kill -9``, say)."""
    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()
