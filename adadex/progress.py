"""Progress bars for long work: tqdm, redrawn in place on a terminal or in a notebook, and at most one
line every :data:`LOG_INTERVAL_S` seconds when the output is a file or a pipe (a ``nohup`` log, CI),
where each redraw of a bar would stay behind as a line of its own.

>>> import io
>>> log = io.StringIO()                              # a file, not a terminal
>>> bar = progress_bar(total=3, file=log, desc="work")
>>> bar.mininterval == LOG_INTERVAL_S
True
>>> for _ in range(3):
...     bar.update()
>>> bar.close()
>>> "3/3" in log.getvalue()                          # the last state is always written
True
"""

from __future__ import annotations

import sys

from tqdm.auto import tqdm as _tqdm

#: seconds between the lines of a bar written to a file or a pipe
LOG_INTERVAL_S = 30.0
#: tqdm.auto chose its notebook widget (Jupyter), which redraws in place whatever the stream says
_NOTEBOOK = any("notebook" in c.__module__ for c in _tqdm.__mro__)


def progress_bar(iterable=None, **kwargs):
    """``tqdm(iterable, **kwargs)``, throttled to a line every :data:`LOG_INTERVAL_S` seconds when its
    output (``file``, default stderr) is not a terminal; a ``mininterval`` given is kept."""
    out = kwargs.get("file") or sys.stderr
    if not _NOTEBOOK and not _isatty(out):
        kwargs.setdefault("mininterval", LOG_INTERVAL_S)
        kwargs["maxinterval"] = max(kwargs.get("maxinterval", 10.0), kwargs["mininterval"])
    return _tqdm(iterable, **kwargs)


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):         # no isatty, or a closed stream
        return False
