"""Recordings as CSV files, one file per sequence: the format, its reader and its writer.

Each file has a header ``time, cmd_<joint>…, pos_<joint>…`` and optionally ``vel_<joint>…``
(columns in any order, ``#`` lines are comments). All files of a recording must have identical
``time`` columns and the same joints. The file name is the sequence label, percent-encoded
(``if_pip/loaded`` ↔ ``if_pip%2Floaded.csv``). CSV carries neither ``initial_qpos`` nor ``meta``:
reading a CSV recording gives their defaults. Numbers are written with Python's shortest round-trip
repr, so CSV round trips are bit-exact too.

Use :func:`adadex.data.recording.from_csv` / :func:`~adadex.data.recording.to_csv` (or
:func:`~adadex.data.recording.load_recording`); this module receives the
:class:`~adadex.data.recording.Recording` class from there instead of importing it, so the
dependency runs one way only.

Example
-------
>>> csv_file_name("if_pip/loaded")
'if_pip%2Floaded.csv'
"""

from __future__ import annotations

import csv
import io
import os
import re
from pathlib import Path
from urllib.parse import quote, unquote

import numpy as np

from adadex.data.recording_errors import (
    JointNameError,
    RecordingError,
    RecordingFileError,
    TimeAxisError,
    prefixed,
    unknown_joint,
)
from adadex.io import write_temp
from adadex.sim.robot import JOINT_NAMES

_CSV_PREFIXES = ("cmd", "pos", "vel")


def _natural_key(p: Path):
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", p.name)]


def _csv_files(paths) -> list[Path]:
    if isinstance(paths, (str, os.PathLike)):
        p = Path(paths)
        if p.is_dir():
            files = sorted((q for q in p.iterdir() if q.suffix.lower() == ".csv" and q.is_file()), key=_natural_key)
            if not files:
                raise RecordingFileError(f"{p}: directory contains no .csv files")
            return files
        return [p]
    files = [Path(p) for p in paths]
    if not files:
        raise RecordingFileError("from_csv: no files given")
    return files


def _parse_header(header: list[str], path: Path) -> tuple[int, list[str], dict[str, dict[str, int]]]:
    """Column of ``time``, joint order (as the cmd_ columns), and {prefix: {joint: column}}."""
    names = [h.strip() for h in header]
    seen: dict[str, int] = {}
    for c, n in enumerate(names):
        if n in seen:
            raise RecordingFileError(f"{path}: duplicate column {n!r} (columns {seen[n] + 1} and {c + 1})")
        seen[n] = c
    if "time" not in seen:
        raise RecordingFileError(f"{path}: missing column 'time' (header: {', '.join(names)})")
    cols: dict[str, dict[str, int]] = {p: {} for p in _CSV_PREFIXES}
    order: list[str] = []
    for c, n in enumerate(names):
        if n == "time":
            continue
        prefix, _, joint = n.partition("_")
        if prefix not in _CSV_PREFIXES or not joint:
            raise RecordingFileError(
                f"{path}: unexpected column {n!r} (column {c + 1}); expected time, cmd_<joint>, pos_<joint> "
                f"and optionally vel_<joint>")
        if joint not in JOINT_NAMES:
            raise unknown_joint(joint, f"{path}: column {n!r} (column {c + 1})")
        cols[prefix][joint] = c
        if prefix == "cmd":
            order.append(joint)
    if not order:
        raise RecordingFileError(f"{path}: no cmd_<joint> columns (header: {', '.join(names)})")
    for prefix in ("pos", "vel"):
        if prefix == "vel" and not cols["vel"]:
            continue
        for j in order:
            if j not in cols[prefix]:
                raise RecordingFileError(f"{path}: joint {j!r} has column cmd_{j} but no {prefix}_{j}")
        for j in cols[prefix]:
            if j not in cols["cmd"]:
                raise RecordingFileError(f"{path}: column {prefix}_{j} has no matching cmd_{j}")
    return seen["time"], order, cols


def _read_csv(path: Path):
    """(time, joints, cmd (T, J), pos (T, J), vel (T, J) or None) of one CSV file."""
    with open(path, newline="", encoding="utf-8-sig") as f:
        rows = [(n, r) for n, r in enumerate(csv.reader(f), start=1)
                if r and any(x.strip() for x in r) and not r[0].lstrip().startswith("#")]
    if not rows:
        raise RecordingFileError(f"{path}: empty file (no header)")
    (_, header), body = rows[0], rows[1:]
    tcol, joints, cols = _parse_header(header, path)
    for line, r in body:
        if len(r) != len(header):
            raise RecordingFileError(f"{path} line {line}: expected {len(header)} values, got {len(r)}")
    try:
        data = np.array([r for _, r in body], dtype=np.float64).reshape(len(body), len(header))
    except ValueError:
        for line, r in body:
            for c, v in enumerate(r):
                try:
                    float(v)
                except ValueError:
                    raise RecordingFileError(
                        f"{path} line {line}, column {header[c].strip()!r}: cannot parse {v!r} as a number") from None
        raise

    def pick(prefix):
        return data[:, [cols[prefix][j] for j in joints]]

    return data[:, tcol], tuple(joints), pick("cmd"), pick("pos"), pick("vel") if cols["vel"] else None


def read_csv(recording_type, paths, label=None):
    """Read CSV files, one sequence per file, into a ``recording_type`` (the Recording class).

    ``paths``: a file, a list of files (sequence order), or a directory (all ``*.csv`` in natural
    name order). ``label``: a label, or a list with one per file; default: each file's name
    without ``.csv``, percent-decoded (as written by :func:`write_csv`). Every file must have the
    same joints (in any column order; the first file's order is used) and an identical ``time``
    column. Errors name the file; nothing is returned unless every file is valid.
    """
    files = _csv_files(paths)
    if label is None:
        labels = [unquote(p.stem) for p in files]
    elif isinstance(label, str):
        if len(files) != 1:
            raise RecordingError(f"label: got one label {label!r} for {len(files)} files; pass a list of labels")
        labels = [label]
    else:
        labels = list(label)
        if len(labels) != len(files):
            raise RecordingError(f"label: expected {len(files)} labels (one per file), got {len(labels)}")
    seqs = []
    for p, lab in zip(files, labels):
        try:
            t, joints, cmd, pos, vel = _read_csv(p)
            one = recording_type(time=t, joint_names=joints, command=cmd[None], joint_pos=pos[None],
                            joint_vel=None if vel is None else vel[None], sequence_labels=(lab,))
        except RecordingError as e:
            raise e if str(e).startswith(str(p)) else prefixed(e, p) from None
        seqs.append((p, one))
    p0, first = seqs[0]
    for p, r in seqs[1:]:
        if set(r.joint_names) != set(first.joint_names):
            missing = sorted(set(first.joint_names) - set(r.joint_names))
            extra = sorted(set(r.joint_names) - set(first.joint_names))
            raise JointNameError(
                f"{p}: joints differ from {p0} (missing: {', '.join(missing) or 'none'}; "
                f"extra: {', '.join(extra) or 'none'})")
        if (r.joint_vel is None) != (first.joint_vel is None):
            has, lacks = (p, p0) if r.joint_vel is not None else (p0, p)
            raise RecordingFileError(f"{p}: {has} has vel_ columns but {lacks} does not; all files or none")
        if r.time.shape != first.time.shape:
            raise TimeAxisError(f"{p}: {r.num_steps} samples but {p0} has {first.num_steps}; time must be identical")
        diff = np.flatnonzero(r.time != first.time)
        if diff.size:
            k = diff[0]
            raise TimeAxisError(
                f"{p}: time differs from {p0} at time index {k} ({float(r.time[k])!r} vs {float(first.time[k])!r} s); "
                f"every file of a recording must have an identical time column")
    aligned = [r.subset(joints=first.joint_names) for _, r in seqs]

    def stack(name):
        return np.stack([getattr(r, name)[0] for r in aligned])

    return recording_type(
        time=first.time,
        joint_names=first.joint_names,
        command=stack("command"),
        joint_pos=stack("joint_pos"),
        joint_vel=None if first.joint_vel is None else stack("joint_vel"),
        sequence_labels=tuple(labels),
    )


def _csv_text(rec, s: int) -> str:
    header = ["time"] + [f"{p}_{j}" for p in ("cmd", "pos", "vel") for j in rec.joint_names
                         if p != "vel" or rec.joint_vel is not None]
    parts = [rec.time[:, None], rec.command[s], rec.joint_pos[s]]
    if rec.joint_vel is not None:
        parts.append(rec.joint_vel[s])
    buf = io.StringIO()
    buf.write(",".join(header) + "\n")
    for row in np.hstack(parts).tolist():
        buf.write(",".join(map(repr, row)) + "\n")
    return buf.getvalue()


def csv_file_name(label: str) -> str:
    """The file name :func:`write_csv` gives a sequence: its label percent-encoded, plus ``.csv``."""
    return quote(label, safe="") + ".csv"


def write_csv(rec, directory) -> list[Path]:
    """Write one CSV file per sequence of the recording ``rec`` into ``directory`` (created).

    Everything is validated and rendered before anything is written; each file is written to a
    temporary file and renamed into place, so no file is ever partial. ``initial_qpos`` and
    ``meta`` are not written (see the module docstring). Returns the paths in sequence order.
    """
    rec.validate()
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise RecordingFileError(f"{directory}: exists and is not a directory")
    names = [csv_file_name(lab) for lab in rec.sequence_labels]
    folded: dict[str, str] = {}
    for lab, n in zip(rec.sequence_labels, names):
        if n.lower() in folded:
            raise RecordingError(
                f"sequence_labels: {folded[n.lower()]!r} and {lab!r} would be written to files whose names differ "
                f"only in case, which collide on case-insensitive file systems")
        folded[n.lower()] = lab
    texts = [_csv_text(rec, s) for s in range(rec.num_sequences)]
    paths = [directory / n for n in names]
    directory.mkdir(parents=True, exist_ok=True)
    temps: list[Path] = []
    try:
        for p, text in zip(paths, texts):
            temps.append(write_temp(p, lambda f, text=text: f.write(text.encode("utf-8"))))
        for tmp, p in zip(temps, paths):
            os.replace(tmp, p)
    except BaseException:
        for tmp in temps:
            tmp.unlink(missing_ok=True)
        raise
    return paths
