"""What the benchmarks share: a dataset to measure on (the given folder, or the ``tiny`` preset built
into a temporary folder) and where results go."""

from __future__ import annotations

import contextlib
import tempfile
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


@contextlib.contextmanager
def dataset_or_tiny(dataset: Path | None):
    """Yield ``dataset``, or a ``tiny`` dataset built for the ``with`` block when it is ``None``."""
    if dataset is not None:
        yield Path(dataset)
        return
    from adadex.data.build import build_dataset

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "tiny"
        build_dataset("tiny", path, seed=4, progress=False)
        yield path
