"""Atomic writes, used for every file and output folder adadex writes.

A file is written to a temporary file in the same folder, flushed to disk, then renamed over the
target, so a reader never sees half a file and a failure leaves the old file (or none) in place.

An output *folder* (a dataset, a comparison, a diagnosis) is written the same way as one unit
(:func:`output_folder`): into a temporary sibling folder, then swapped in with renames, so the
folder is complete or absent and never mixes files of two runs. Each carries a small marker file
(:data:`OUTPUT_MARKER`) naming its kind; an existing target that is not an adadex output of the same
kind (a folder of the user's own files, a file) is refused unless ``force=True``, so no user data is
replaced by mistake. Temporary folders left by a killed run are removed on the next write, and so are
the temporary files of a killed file write (named with the writer's process id, so that a write still
running elsewhere keeps its own).

An output *file* (an MJCF export, an excitation plan, a simulated recording) is guarded the same way
(:func:`output_file`): it carries a marker beside it, ``.NAME`` + :data:`FILE_MARKER_SUFFIX`, naming
its kind and the SHA-256 of the file as written. An existing file is replaced only when its marker
names the same kind and its content is still what was written (a file the user wrote, or edited
since, is refused), or with ``force=True``. Earlier outputs are recognized by the marker the command
wrote, never by the shape of their content. A folder is never replaced by a file.

An output folder that is written *in place*, file by file as the work goes (a training run's ``out``,
the Table 1 pipeline's), cannot be swapped in whole; it is checked the same way before any work
(:func:`check_output_dir`: absent, empty, marked as the same command's, or ``force``; a file there is
refused) and then marked (:func:`mark_output_dir`). What a rerun into it may do — resume, skip — is
the command's to decide (:func:`adadex.train.checkpoint.check_run`).

Example
-------
>>> import tempfile, pathlib
>>> p = pathlib.Path(tempfile.mkdtemp()) / "out.txt"
>>> _ = atomic_write_text(p, "hello")
>>> p.read_text()
'hello'
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import shutil
import zipfile
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import BinaryIO

from adadex.errors import AdadexError

#: File inside every adadex output folder naming its kind: ``{"kind": "dataset"}``.
OUTPUT_MARKER = ".adadex-output.json"

#: Beside every adadex output file ``NAME``, ``.NAME.adadex-output.json``: ``{"kind": …, "sha256": …}``.
FILE_MARKER_SUFFIX = ".adadex-output.json"


class OutputExistsError(AdadexError, FileExistsError):
    """The output path holds something that is not an adadex output of the kind being written."""


def temp_path(path: Path) -> Path:
    """A fresh temporary sibling of the file ``path``: ``.NAME.p<pid>.<random>.tmp``. The writer's process id
    in the name lets a later write of ``path`` tell a temporary a killed writer left (its process is gone)
    from one being written now (:func:`clean_dead_temporaries`)."""
    return path.parent / f".{path.name}.p{os.getpid()}.{secrets.token_hex(6)}.tmp"


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    if os.name == "nt":                  # os.kill would end the process there: never judge, keep the file
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:                      # another user's process (EPERM) …: alive
        return True
    return True


def clean_dead_temporaries(path) -> list[Path]:
    """Remove the temporary files of ``path`` (:func:`temp_path`) whose writer's process is gone — what a
    killed write (``adadex sysid fit`` stopped with ``kill -9``, a power cut) left beside it — and those
    of earlier versions (``.NAME.<random>.tmp`` files, without a process id). Temporaries of a writer still
    running, in this process or another, are kept. Returns the paths removed."""
    path = Path(path)
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.(?:p(\d+)\.)?[0-9a-f]{{12}}\.tmp$")
    removed = []
    try:
        entries = list(path.parent.iterdir())
    except OSError:
        return removed
    for p in entries:
        m = pattern.match(p.name)
        if not m or p.is_dir() or (m.group(1) is not None and _process_alive(int(m.group(1)))):
            continue
        try:
            p.unlink()
            removed.append(p)
        except OSError:
            pass
    return removed


def _open_new(tmp: Path) -> BinaryIO:
    """Create ``tmp`` exclusively with the usual permissions (mkstemp would make it owner-only)."""
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    return os.fdopen(fd, "wb")


def write_temp(path: Path, write: Callable[[BinaryIO], object]) -> Path:
    """Write a temporary sibling of ``path`` with ``write(file)``; return its path (not yet renamed).
    Temporaries of ``path`` that killed writers left are removed first (:func:`clean_dead_temporaries`)."""
    clean_dead_temporaries(path)
    tmp = temp_path(path)
    try:
        with _open_new(tmp) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


def atomic_write(path, write: Callable[[BinaryIO], object]) -> Path:
    """Write ``path`` atomically with ``write(binary_file)``; creates parent folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = write_temp(path, write)
    try:
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def json_default(obj):
    """``json.dumps(…, default=json_default)``: numpy scalars and arrays as Python numbers and lists
    (anything else is refused, as ``json`` refuses it)."""
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON-serializable")


def atomic_write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`atomic_write`); return the path."""
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`atomic_write`); return the path."""
    return atomic_write(path, lambda f: f.write(data))


# ----------------------------------------------------------------------------------------------
# Output folders


def output_kind(path, recognize: Callable[[Path], bool] | None = None, kind: str = "") -> str | None:
    """The kind of adadex output folder at ``path`` (from its marker), or ``None``.

    ``recognize(path)`` identifies folders of ``kind`` written before markers existed.
    """
    path = Path(path)
    if not path.is_dir():
        return None
    try:
        found = json.loads((path / OUTPUT_MARKER).read_text(encoding="utf-8")).get("kind")
        return found if isinstance(found, str) else None
    except (OSError, ValueError, AttributeError):
        pass
    return kind if _recognized(recognize, path) else None


def _recognized(recognize: Callable[[Path], bool] | None, path: Path) -> bool:
    try:
        return recognize is not None and bool(recognize(path))
    except (OSError, ValueError, KeyError, TypeError, AttributeError, EOFError, zipfile.BadZipFile):
        return False


# ----------------------------------------------------------------------------------------------
# Output files


def file_marker(path) -> Path:
    """Where the marker of the output file ``path`` lives: ``.NAME.adadex-output.json`` beside it."""
    path = Path(path)
    return path.parent / f".{path.name}{FILE_MARKER_SUFFIX}"


def _sha256(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def mark_file(path, kind: str) -> Path:
    """Record the file ``path`` (as it is now) as an adadex output of ``kind``; returns the marker's path."""
    path = Path(path)
    return atomic_write_text(file_marker(path), json.dumps({"kind": kind, "file": path.name, "sha256": _sha256(path)}))


def file_output_kind(path) -> str | None:
    """The kind of adadex output the file ``path`` is, from its marker — ``None`` when it has none, or
    when the file is no longer what was written (replaced or edited since)."""
    path = Path(path)
    try:
        m = json.loads(file_marker(path).read_text(encoding="utf-8"))
        if not path.is_file() or not isinstance(m, dict) or m.get("sha256") != _sha256(path):
            return None
        return m["kind"] if isinstance(m.get("kind"), str) else None
    except (OSError, ValueError, KeyError):
        return None


def check_output_file(path, kind: str, *, force: bool = False, recognize: Callable[[Path], bool] | None = None,
                      option: str = "--force") -> Path:
    """:func:`check_output` for an output that is one file: also refuses a folder at ``path``, even with
    ``force`` (a file never replaces a folder)."""
    path = Path(path)
    if path.is_dir():
        raise OutputExistsError(f"{path} is a folder; give the path of the {kind} file to write (a folder is "
                                f"never replaced by a file, even with {option})")
    return check_output(path, kind, force=force, recognize=recognize, option=option)


@contextlib.contextmanager
def output_file(path, kind: str, *, force: bool = False, option: str = "--force") -> Iterator[Path]:
    """Guard the output file ``path`` of ``kind``: checked on entry (:func:`check_output_file`, before any
    work); the block writes ``path`` (atomically); when it ends without error, the marker is written, so
    the next run of the same command may replace it.

    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "plan.txt"
    >>> with output_file(p, "plan") as path:
    ...     _ = atomic_write_text(path, "1")
    >>> file_output_kind(p)
    'plan'
    >>> with output_file(p, "plan") as path:         # an earlier output of the same kind: replaced
    ...     _ = atomic_write_text(path, "2")
    >>> _ = p.write_text("edited by hand")           # no longer what adadex wrote: refused
    >>> with output_file(p, "plan") as path:  # doctest: +ELLIPSIS
    ...     pass
    Traceback (most recent call last):
    ...
    adadex.io.OutputExistsError: ... exists and is a file that adadex did not write as a plan (or that changed since); ...
    """
    path = check_output_file(path, kind, force=force, option=option)
    yield path
    if path.is_file():
        mark_file(path, kind)


def check_output(path, kind: str, *, force: bool = False, recognize: Callable[[Path], bool] | None = None,
                 option: str = "--force", ignore: Collection[str] = ()) -> Path:
    """Refuse to replace ``path`` unless it is absent, an empty folder, or an adadex ``kind`` output.

    A file at ``path`` is accepted when its marker (:func:`mark_file`) names ``kind`` and it is unchanged
    since, or when ``recognize(path)`` says it is one. ``force=True`` replaces anything. A folder holding
    only entries named in ``ignore`` counts as empty (what the running command itself just put there,
    such as Hydra's ``.hydra/`` and log). Raises :class:`OutputExistsError` naming the path, what is
    there and ``option`` (how to force).
    """
    path = Path(path)
    if force or not (path.exists() or path.is_symlink()):
        return path
    if path.is_dir() and not path.is_symlink():
        found = output_kind(path, recognize, kind)
        if found == kind or not any(p.name not in ignore for p in path.iterdir()):
            return path
        what = f"an adadex {found} output" if found else "a folder that is not an adadex output"
    elif path.is_file():
        found = file_output_kind(path)
        if found == kind or _recognized(recognize, path):
            return path                    # a single-file output of this kind (a patch, a report …)
        what = (f"a file, an adadex {found} output" if found else
                f"a file that adadex did not write as a {kind} (or that changed since)")
    else:
        what = "something that is not a folder"
    article = "an" if kind[:1].lower() in "aeiou" else "a"
    raise OutputExistsError(f"{path} exists and is {what}; refusing to replace it with {article} {kind} "
                            f"(choose another path, or pass {option} to replace it)")


def check_output_dir(path, kind: str, *, force: bool = False, recognize: Callable[[Path], bool] | None = None,
                     option: str = "--force", ignore: Collection[str] = ()) -> Path:
    """:func:`check_output` for an output folder written in place, file by file, as it is made (a training
    run, the Table 1 pipeline) rather than swapped in whole: also refuses a file at ``path``, even with
    ``force`` (a folder never replaces a file). Nothing is written; :func:`claim_output_dir` then marks it."""
    path = Path(path)
    if (path.exists() or path.is_symlink()) and not path.is_dir():
        raise OutputExistsError(f"{path} exists and is not a folder; give a folder for the {kind} (a file is never "
                                f"replaced by a folder, even with {option})")
    return check_output(path, kind, force=force, recognize=recognize, option=option, ignore=ignore)


def claim_output_dir(path, kind: str, *, force: bool = False, recognize: Callable[[Path], bool] | None = None,
                     option: str = "--force") -> Path:
    """:func:`check_output_dir`, then make the folder and mark it (:data:`OUTPUT_MARKER`) as an adadex ``kind``
    output, so the next run of the same command may write into it again.

    >>> import tempfile, pathlib
    >>> run = pathlib.Path(tempfile.mkdtemp()) / "run"
    >>> _ = claim_output_dir(run, "training run")
    >>> output_kind(run), claim_output_dir(run, "training run") == run
    ('training run', True)
    >>> _ = (run.parent / "mine").mkdir(); _ = (run.parent / "mine" / "thesis.tex").write_text("x")
    >>> claim_output_dir(run.parent / "mine", "training run", option="force=true")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    adadex.io.OutputExistsError: ... is a folder that is not an adadex output; ... pass force=true to replace it)
    """
    return mark_output_dir(check_output_dir(path, kind, force=force, recognize=recognize, option=option), kind)


def mark_output_dir(path, kind: str) -> Path:
    """Make the folder ``path`` and mark it as an adadex ``kind`` output (no check: the caller checked it)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    try:
        marked = json.loads((path / OUTPUT_MARKER).read_text(encoding="utf-8")).get("kind") == kind
    except (OSError, ValueError, AttributeError):
        marked = False
    if not marked:
        atomic_write_text(path / OUTPUT_MARKER, json.dumps({"kind": kind}))
    return path


def clean_stale(path) -> list[Path]:
    """Remove the temporary siblings (``.NAME.<hex>.tmp`` / ``.old``) a killed write of ``path`` left."""
    path = Path(path)
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.[0-9a-f]{{12}}\.(tmp|old)$")
    removed = []
    if path.parent.is_dir():
        for p in path.parent.iterdir():
            if pattern.match(p.name):
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p, ignore_errors=True)
                else:
                    p.unlink(missing_ok=True)
                removed.append(p)
    return removed


@contextlib.contextmanager
def output_folder(path, kind: str, *, force: bool = False, recognize: Callable[[Path], bool] | None = None,
                  option: str = "--force", marker: bool = True) -> Iterator[Path]:
    """Write the output folder ``path`` as one unit: yields an empty temporary sibling folder to fill;
    when the block ends without error, the marker is added and the folder is renamed over ``path``
    (the previous one removed only after). On error the temporary folder is removed and ``path``
    is untouched. See :func:`check_output` for what may be replaced. ``marker=False`` leaves the marker
    out, for formats that identify themselves (``recognize``), such as reference datasets.

    >>> import tempfile, pathlib
    >>> out = pathlib.Path(tempfile.mkdtemp()) / "run"
    >>> with output_folder(out, "demo") as tmp:
    ...     _ = (tmp / "a.txt").write_text("1")
    >>> sorted(p.name for p in out.iterdir()), output_kind(out)
    (['.adadex-output.json', 'a.txt'], 'demo')
    >>> with output_folder(out, "demo") as tmp:      # a new run replaces the whole folder
    ...     _ = (tmp / "b.txt").write_text("2")
    >>> sorted(p.name for p in out.iterdir())
    ['.adadex-output.json', 'b.txt']
    """
    path = Path(path)
    check_output(path, kind, force=force, recognize=recognize, option=option)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_stale(path)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    tmp.mkdir()
    try:
        yield tmp
        if marker:
            atomic_write_text(tmp / OUTPUT_MARKER, json.dumps({"kind": kind}))
        if path.exists() or path.is_symlink():
            old = path.parent / f".{path.name}.{secrets.token_hex(6)}.old"
            os.replace(path, old)
            try:
                os.replace(tmp, path)
            except BaseException:
                os.replace(old, path)
                raise
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old, ignore_errors=True)
            else:
                old.unlink(missing_ok=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
