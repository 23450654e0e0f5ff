"""What the benchmarks share: a dataset to measure on (the given folder, or the ``tiny`` preset built
into a temporary folder) and where results go.

Every benchmark writes its JSON result through :func:`write_result`, guarded as one adadex output file
(:mod:`adadex.io`, kind ``"benchmark NAME"``, a marker beside it): an earlier result of the same benchmark
is replaced; anything else at ``--out`` (a file of the user's, another benchmark's result, a folder) is
refused with one line and exit code 2 unless ``--force``. :func:`check_result` runs the same check before
the benchmark's work, so a refusal costs nothing. Results in :data:`RESULTS` written before the markers
existed (no marker beside them; the folder is the benchmarks' own and not tracked) count as earlier results."""

from __future__ import annotations

import contextlib
import json
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


def _kind(name: str) -> str:
    return f"benchmark {name}"


def _unmarked_in_results(path: Path) -> bool:
    """An unmarked file in :data:`RESULTS`: a result written before the markers existed."""
    from adadex.io import file_marker

    path = Path(path)
    return path.resolve().parent == RESULTS and not file_marker(path).exists()


def check_result(path, *, name: str, force: bool = False) -> Path:
    """Refuse ``path`` as the result file of the benchmark ``name`` unless it is absent, an earlier result
    of it, or ``force``: ``SystemExit(2)`` after one line on stderr (``benchmarks/NAME.py: error: …``, as
    :func:`adadex.errors.report_error` reports bad input). Call it right after parsing the arguments."""
    from adadex.errors import AdadexError, report_error
    from adadex.io import check_output_file

    try:
        return check_output_file(path, _kind(name), force=force, recognize=_unmarked_in_results)
    except AdadexError as e:
        raise SystemExit(report_error(f"benchmarks/{name}.py", e)) from None


def result_arguments(parser, name: str):
    """Add ``--out`` (default ``results/NAME.json``) and ``--force`` to a benchmark's argument parser, parse
    ``argv`` and check ``--out`` before any work (:func:`check_result`); returns a function of ``argv``
    giving the parsed arguments."""
    parser.add_argument("--out", type=Path, default=RESULTS / f"{name}.json")
    parser.add_argument("--force", action="store_true",
                        help="replace --out even if it is not an earlier result of this benchmark")

    def parse(argv=None):
        args = parser.parse_args(argv)
        check_result(args.out, name=name, force=args.force)
        return args
    return parse


def write_result(path, result: dict, *, name: str, force: bool = False, indent: int = 1,
                 ensure_ascii: bool = True) -> Path:
    """Write ``result`` as JSON to ``path`` (atomically, parent folders made) and mark it as the benchmark
    ``name``'s, so its next run may replace it; checked first (:func:`check_result`)."""
    from adadex.io import atomic_write_text, mark_file

    path = check_result(path, name=name, force=force)
    atomic_write_text(path, json.dumps(result, indent=indent, ensure_ascii=ensure_ascii))
    mark_file(path, _kind(name))
    return path


def refuse(name: str, message) -> SystemExit:
    """The benchmark ``name``'s refusal of bad input: one line on stderr (``benchmarks/NAME.py: error: …``)
    and exit code 2, as :func:`check_result` and every adadex command report it. ``message``: text or an
    :class:`~adadex.errors.AdadexError`. Raise what it returns."""
    from adadex.errors import AdadexError, ConfigError, report_error

    error = message if isinstance(message, AdadexError) else ConfigError(str(message))
    return SystemExit(report_error(f"benchmarks/{name}.py", error))


def settings(text: str, defaults, flag: str, name: str) -> dict:
    """``"k=v,k=v"`` → ``{k: v}``, each value of its default's type in ``defaults`` (a config instance;
    ``true``/``false`` for switches, ``lo:hi`` for a range); a key it lacks, or a value not of its type,
    ends the benchmark ``name`` (:func:`refuse`) naming ``flag``."""
    out = {}
    for kv in filter(None, text.split(",")):
        k, eq, v = kv.partition("=")
        if not eq or not hasattr(defaults, k):
            raise refuse(name, f"{flag}: {kv!r} is not k=v with k a {type(defaults).__name__} setting")
        default = getattr(defaults, k)
        if isinstance(default, bool):
            if v not in ("true", "false"):
                raise refuse(name, f"{flag}: {k} is a switch, true or false, got {v!r}")
            out[k] = v == "true"
            continue
        if isinstance(default, tuple) and default and all(isinstance(x, float) for x in default):   # lo:hi
            try:
                parts = tuple(float(x) for x in v.split(":"))
            except ValueError:
                parts = ()
            if len(parts) != len(default):
                raise refuse(name, f"{flag}: {k} is a range lo:hi of numbers, got {v!r}")
            out[k] = parts
            continue
        if not isinstance(default, (int, float, str)):
            raise refuse(name, f"{flag}: {k} is not a number, switch or range and cannot be set here")
        try:
            out[k] = type(default)(v)
        except (TypeError, ValueError):
            kind = {int: "an integer", float: "a number"}.get(type(default), type(default).__name__)
            raise refuse(name, f"{flag}: {k} must be {kind}, got {v!r}") from None
    return out
