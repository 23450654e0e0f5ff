"""Atomic writes, used for every file and output folder adadex writes.

A file is written to a temporary file in the same folder, flushed to disk, then renamed over the
target, so a reader never sees half a file and a failure leaves the old file (or none) in place.

An output *folder* (a dataset, a comparison, a diagnosis) is written the same way as one unit
(:func:`output_folder`): into a temporary sibling folder, then swapped in with renames, so the
folder is complete or absent and never mixes files of two runs. Each carries a small marker file
(:data:`OUTPUT_MARKER`) naming its kind; an existing target that is not an adadex output of the same
kind (a folder of the user's own files, a file) is refused unless ``force=True``, so no user data is
replaced by mistake. Temporary folders left by a killed run are removed on the next write.

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
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

from adadex.errors import AdadexError

#: File inside every adadex output folder naming its kind: ``{"kind": "dataset"}``.
OUTPUT_MARKER = ".adadex-output.json"


class OutputExistsError(AdadexError, FileExistsError):
    """The output path holds something that is not an adadex output of the kind being written."""


def temp_path(path: Path) -> Path:
    return path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"


def _open_new(tmp: Path) -> BinaryIO:
    """Create ``tmp`` exclusively with the usual permissions (mkstemp would make it owner-only)."""
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    return os.fdopen(fd, "wb")


def write_temp(path: Path, write: Callable[[BinaryIO], object]) -> Path:
    """Write a temporary sibling of ``path`` with ``write(file)``; return its path (not yet renamed)."""
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


def atomic_write_text(path, text: str) -> Path:
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def atomic_write_bytes(path, data: bytes) -> Path:
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


def check_output(path, kind: str, *, force: bool = False, recognize: Callable[[Path], bool] | None = None,
                 option: str = "--force") -> Path:
    """Refuse to replace ``path`` unless it is absent, an empty folder, or an adadex ``kind`` output.

    A file at ``path`` is accepted when ``recognize(path)`` says it is one (single-file outputs).
    ``force=True`` replaces anything. Raises :class:`OutputExistsError` naming the path, what is
    there and ``option`` (how to force).
    """
    path = Path(path)
    if force or not (path.exists() or path.is_symlink()):
        return path
    if path.is_dir() and not path.is_symlink():
        found = output_kind(path, recognize, kind)
        if found == kind or not any(path.iterdir()):
            return path
        what = f"an adadex {found} output" if found else "a folder that is not an adadex output"
    elif path.is_file() and _recognized(recognize, path):
        return path                        # a single-file output of this kind (a patch, a report …)
    else:
        what = "a file" if path.is_file() else "something that is not a folder"
    raise OutputExistsError(f"{path} exists and is {what}; refusing to replace it with a {kind} "
                            f"(choose another path, or pass {option} to replace it)")


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
