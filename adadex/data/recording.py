"""Recordings of commanded and measured joint trajectories: the sysid workbench's data format.

A :class:`Recording` holds ``S`` sequences of ``T`` samples for ``J`` of the robot's joints: the
joint-position targets that were sent (``command``) and the joint positions that were measured
(``joint_pos``), optionally measured velocities. It is what system identification compares the
simulator against, whether the data came from the real robot or from a simulated "truth" model.
Every recording is validated when it is built, so code downstream (replay, fitting, diagnosis)
never has to guard against NaNs, ragged time axes, unknown joints or commands the servos would
refuse — and errors say *what* is wrong and *where* (field, sequence, time index, joint, file).
A recording is immutable: its arrays are read-only copies.

Timing convention (zero-order hold)
-----------------------------------
``time`` is uniform (spacing ``dt``) and strictly increasing; its start is arbitrary.
``joint_pos[s, k]`` is measured at ``time[k]``. ``command[s, k]`` is sent at ``time[k]`` and held
constant until ``time[k + 1]`` (zero-order hold), so the last command is never acted on within
the recording. Each sequence starts at rest in ``initial_qpos[s]``, the full 22-joint configuration
(in :data:`~adadex.sim.robot.JOINT_NAMES` order); joints that are not recorded hold that value
as their command (:meth:`Recording.full_command`).

File format (``.npz``, :meth:`Recording.save` / :meth:`Recording.load`)
------------------------------------------------------------------------
=================== ============ ==========================================================
key                 shape        meaning
=================== ============ ==========================================================
``time``            (T,)         seconds, uniform, strictly increasing, T ≥ 2
``joint_names``     (J,) str     a subset of JOINT_NAMES, any order, no duplicates, J ≥ 1
``command``         (S, T, J)    joint-position targets sent, rad, within the joint limits
``joint_pos``       (S, T, J)    measured joint positions, rad (the workbench takes them within
                                 the joint limits ± MEASURED_RANGE_MARGIN: check_measured_range)
``joint_vel``       (S, T, J)    optional: measured joint velocities, rad/s
``sequence_labels`` (S,) str     optional: unique names, default ``seq0, seq1, …``
``initial_qpos``    (S, 22)      optional: configuration at t = time[0]; default: the first
                                 measured sample for recorded joints, HOME_QPOS for the rest
``meta``            () str       optional: JSON object, free-form (how the data was made);
                                 its ``sequences``, if any, one object per sequence
=================== ============ ==========================================================

All arrays are float64, strings are stored as numpy unicode arrays: files load with
``allow_pickle=False``. Saving and loading is bit-exact; ``meta`` is normalised through JSON when
the recording is built (tuples become lists, numpy scalars Python numbers), so a loaded recording
equals the saved one.

A user's model
--------------
A recording of a robot other than adadex's names the servoed joints of that model: pass its joint
table (``robot=``, a :class:`~adadex.sim.model_source.RobotTable`) when building or loading.
Joint names, limits and the width of ``initial_qpos`` (one column per servoed joint, in the
table's order) are then the model's, and unrecorded joints default to its home pose.

CSV (:func:`from_csv` / :func:`to_csv`)
---------------------------------------
One file per sequence, ``time, cmd_<joint>…, pos_<joint>…[, vel_<joint>…]``, named by the sequence
label; bit-exact round trips, without ``initial_qpos`` and ``meta``. The format, its reader and
its writer are in :mod:`adadex.data.recording_csv`; the errors of both formats in
:mod:`adadex.data.recording_errors`. Everything is importable from here.

Example
-------
>>> import numpy as np
>>> from adadex.data.recording import Recording
>>> cmd = np.linspace(0.0, 0.4, 5).reshape(1, 5, 1)
>>> rec = Recording(time=np.arange(5) * 0.01, joint_names=("if_pip",), command=cmd, joint_pos=cmd)
>>> rec.num_sequences, rec.num_steps, rec.num_joints, rec.sequence_labels
(1, 5, 1, ('seq0',))
>>> rec.full_command().shape
(1, 5, 22)
>>> Recording(time=np.arange(5) * 0.01, joint_names=("if_pip",), command=cmd + 2.0, joint_pos=cmd)
... # doctest: +ELLIPSIS
Traceback (most recent call last):
...
adadex.data.recording_errors.CommandLimitError: command: 2.0 rad for joint 'if_pip' in sequence 0 ('seq0') at ...
"""

from __future__ import annotations

import difflib
import functools
import json
import unicodedata
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adadex.data import recording_csv
from adadex.data.recording_csv import csv_file_name
from adadex.data.recording_errors import (
    CommandLimitError,
    JointNameError,
    MeasurementRangeError,
    NonFiniteValueError,
    RecordingError,
    RecordingFileError,
    RecordingShapeError,
    TimeAxisError,
    UnknownJointNameError,
    prefixed,
    unknown_joint,
)
from adadex.errors import ConfigTypeError
from adadex.io import atomic_write, json_default
from adadex.sim.robot import HOME_QPOS, JOINT_NAMES, NUM_JOINTS, joint_index, joint_limits

__all__ = ["Recording", "load_recording", "from_csv", "to_csv", "csv_file_name", "LIMIT_TOLERANCE",
           "TIME_RELATIVE_TOLERANCE", "SAMPLE_PERIOD_RANGE", "INITIAL_QPOS_TOLERANCE", "REQUIRED_KEYS", "OPTIONAL_KEYS", "RecordingError", "RecordingShapeError",
           "NonFiniteValueError", "TimeAxisError", "JointNameError", "UnknownJointNameError", "CommandLimitError",
           "MeasurementRangeError", "RecordingFileError", "MEASURED_RANGE_MARGIN"]

#: Commands may exceed the joint limits by this much (rad) before a recording is rejected.
LIMIT_TOLERANCE = 1e-6
#: Samples may deviate from uniform spacing by this fraction of ``dt``.
TIME_RELATIVE_TOLERANCE = 1e-6
#: Plausible sample periods (s), inclusive; outside them ``time`` is almost surely not in seconds (a
#: period of 16.7 is milliseconds). Assign another pair here to accept unusual data.
SAMPLE_PERIOD_RANGE = (1e-4, 1.0)
#: ``initial_qpos`` may exceed the joint limits by this much (rad): it is often a measured sample.
INITIAL_QPOS_TOLERANCE = 0.02
#: Measured positions (``joint_pos``) are not held to the joint limits — a joint may be pushed past them,
#: an encoder may be offset — but one farther than this outside them (rad, or m for a slide joint) is no
#: reading of the joint: a unit slip (degrees, encoder counts) or a corrupt value, refused.
MEASURED_RANGE_MARGIN = float(np.pi)

REQUIRED_KEYS = ("time", "joint_names", "command", "joint_pos")
OPTIONAL_KEYS = ("joint_vel", "sequence_labels", "initial_qpos", "meta")


def _float_array(value, name: str) -> np.ndarray:
    """A read-only float64 copy of ``value``; the caller's array is never aliased or modified."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise RecordingError(f"{name}: cannot convert to a float array ({e})") from None
    arr.setflags(write=False)
    return arr


def _str_tuple(value, name: str, error=RecordingError) -> tuple[str, ...]:
    if isinstance(value, (str, bytes)):
        raise error(f"{name}: expected a sequence of strings, got the single string {value!r}")
    try:
        items = list(value)
    except TypeError:
        raise error(f"{name}: expected a sequence of strings, got {type(value).__name__}") from None
    out = []
    for i, v in enumerate(items):
        if not isinstance(v, str):
            raise error(f"{name}[{i}]: expected a string, got {type(v).__name__} {v!r}")
        out.append(str(v))
    return tuple(out)


@dataclass(frozen=True, eq=False, repr=False)
class Recording:
    """Commanded and measured trajectories of ``S`` sequences × ``T`` samples × ``J`` joints.

    See the module docstring for the meaning of each field and the timing convention. Building a
    recording copies and validates every field (:meth:`validate`) and fills the defaults of
    ``sequence_labels`` (``seq0, seq1, …``) and ``initial_qpos``. ``initial_qpos`` may be given as
    (22,) for all sequences.

    Attributes:
        time: (T,) sample times, s: uniform, strictly increasing, T ≥ 2.
        joint_names: the J recorded joints (a subset of the robot's, any order, no duplicates).
        command: (S, T, J) joint-position targets sent, rad (zero-order hold), within the limits.
        joint_pos: (S, T, J) measured joint positions, rad.
        joint_vel: optional (S, T, J) measured joint velocities, rad/s.
        sequence_labels: S unique names (default ``seq0, seq1, …``).
        initial_qpos: (S, 22) configuration at ``time[0]`` (the model's width for a user's model;
            (22,) is broadcast); default: the first measured sample for recorded joints, the home
            pose for the rest.
        meta: free-form JSON object (how the data was made), normalised through JSON.
        robot: the joint table of a user's model (None: adadex's robot).
    """

    time: np.ndarray
    joint_names: tuple[str, ...]
    command: np.ndarray
    joint_pos: np.ndarray
    joint_vel: np.ndarray | None = None
    sequence_labels: tuple[str, ...] = ()
    initial_qpos: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    #: The joint table of a user's model (None: adadex's robot); see the module docstring.
    robot: object = None

    def __post_init__(self):
        put = object.__setattr__
        put(self, "time", _float_array(self.time, "time"))
        put(self, "joint_names", _str_tuple(self.joint_names, "joint_names", JointNameError))
        put(self, "command", _float_array(self.command, "command"))
        put(self, "joint_pos", _float_array(self.joint_pos, "joint_pos"))
        if self.joint_vel is not None:
            put(self, "joint_vel", _float_array(self.joint_vel, "joint_vel"))
        labels = () if self.sequence_labels is None else self.sequence_labels
        labels = _str_tuple(labels, "sequence_labels")
        if not labels and self.command.ndim == 3:
            labels = tuple(f"seq{i}" for i in range(self.command.shape[0]))
        put(self, "sequence_labels", labels)
        if self.robot is not None and self.robot.builtin:
            put(self, "robot", None)
        if self.initial_qpos is not None:
            q = _float_array(self.initial_qpos, "initial_qpos")
            if q.shape == (self._width,) and self.command.ndim == 3:
                q = _float_array(np.broadcast_to(q, (self.command.shape[0], self._width)), "initial_qpos")
            put(self, "initial_qpos", q)
        put(self, "meta", self._normalised_meta(self.meta))

        self.validate()

        if self.initial_qpos is None:
            q = np.tile(HOME_QPOS if self.robot is None else self.robot.home, (self.num_sequences, 1))
            q[:, self.joint_indices] = self.joint_pos[:, 0, :]
            q.setflags(write=False)
            put(self, "initial_qpos", q)

    @property
    def _width(self) -> int:
        return NUM_JOINTS if self.robot is None else self.robot.num_joints

    @property
    def _all_joints(self) -> tuple[str, ...]:
        return JOINT_NAMES if self.robot is None else self.robot.names

    def _unknown(self, name, where: str):
        if self.robot is None:
            return unknown_joint(name, where)
        from adadex.sim.robot import UnknownJointError

        err = UnknownJointError.for_model(name, self.robot.names, self.robot.model_id)
        return UnknownJointNameError(f"{where}: {err.args[0]}")

    @staticmethod
    def _normalised_meta(meta) -> dict:
        if meta is None:
            return {}
        if not isinstance(meta, Mapping):
            raise RecordingError(f"meta: expected a dict, got {type(meta).__name__}")
        try:
            return json.loads(json.dumps(dict(meta), default=json_default))
        except (TypeError, ValueError) as e:
            raise RecordingError(f"meta: not JSON-serializable ({e})") from None

    # ------------------------------------------------------------------ validation

    def validate(self) -> None:
        """Check every field; raise a :class:`RecordingError` subclass naming the first problem.

        Runs when a recording is built and again before it is written. An empty
        ``sequence_labels`` or a ``None`` ``initial_qpos`` counts as "default" and passes.
        """
        self._check_shapes()
        self._check_joint_names()      # before initial_qpos's width, which depends on the model's joints
        self._check_qpos_shape()
        self._check_meta_sequences()
        self._check_labels()
        self._check_time()
        for name in ("command", "joint_pos", "joint_vel"):
            arr = getattr(self, name)
            if arr is not None:
                self._check_finite(name, arr)
        self._check_limits()
        if self.initial_qpos is not None:
            self._check_finite_qpos()
            self._check_qpos_limits()

    def _where(self, s: int) -> str:
        if self.sequence_labels:
            return f"sequence {s} ({self.sequence_labels[s]!r})"
        return f"sequence {s}"

    def _check_shapes(self) -> None:
        if self.time.ndim != 1:
            raise RecordingShapeError(f"time: expected shape (T,), got {self.time.shape}")
        T = self.time.shape[0]
        if T < 2:
            raise TimeAxisError(f"time: a recording needs at least 2 samples, got {T}")
        if self.command.ndim != 3:
            raise RecordingShapeError(f"command: expected 3 dimensions (S, T, J), got shape {self.command.shape}")
        S, J = self.command.shape[0], len(self.joint_names)
        if S < 1:
            raise RecordingShapeError(f"command: a recording needs at least 1 sequence, got shape {self.command.shape}")
        if J < 1:
            raise JointNameError("joint_names: a recording needs at least 1 joint, got none")
        expected = (S, T, J)
        for name in ("command", "joint_pos", "joint_vel"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != expected:
                raise RecordingShapeError(
                    f"{name}: expected shape (S, T, J) = {expected} (S from command, T from time, "
                    f"J from joint_names), got {arr.shape}")
        if self.sequence_labels and len(self.sequence_labels) != S:
            raise RecordingShapeError(
                f"sequence_labels: expected {S} labels (one per sequence), got {len(self.sequence_labels)}")

    def _check_qpos_shape(self) -> None:
        S, W = self.num_sequences, self._width
        if self.initial_qpos is not None and self.initial_qpos.shape != (S, W):
            raise RecordingShapeError(
                f"initial_qpos: expected shape (S, {W}) = {(S, W)} (or ({W},) for all sequences), "
                f"got {self.initial_qpos.shape}")

    def _check_joint_names(self) -> None:
        seen: dict[str, int] = {}
        for i, n in enumerate(self.joint_names):
            if n not in self._all_joints:
                raise self._unknown(n, f"joint_names[{i}]")
            if n in seen:
                raise JointNameError(f"joint_names: duplicate joint {n!r} at positions {seen[n]} and {i}")
            seen[n] = i

    def _check_meta_sequences(self) -> None:
        """``meta["sequences"]`` (one description per sequence, as :mod:`adadex.sysid.excite` writes) must
        match the arrays: the workbench picks each joint's sequences and the held-out ones from it."""
        seqs = self.meta.get("sequences")
        if not seqs:                   # absent (or empty): the workbench treats every sequence alike
            return
        S = self.num_sequences
        if not isinstance(seqs, list):
            raise RecordingError(f"meta['sequences']: expected a list with one entry per sequence ({S}), "
                                 f"got {type(seqs).__name__}")
        if len(seqs) != S:
            raise RecordingShapeError(f"meta['sequences']: {len(seqs)} entries, but the arrays hold {S} sequences "
                                      f"(command has shape {self.command.shape}); one entry per sequence expected")
        for i, entry in enumerate(seqs):
            if not isinstance(entry, dict):
                raise RecordingError(f"meta['sequences'][{i}]: expected an object (a dict), got "
                                     f"{type(entry).__name__} {entry!r}")
            joint = entry.get("joint")
            if joint is not None and not isinstance(joint, str):
                raise RecordingError(f"meta['sequences'][{i}]['joint']: expected a joint name, got {joint!r}")

    def _check_labels(self) -> None:
        seen: dict[str, int] = {}
        for i, lab in enumerate(self.sequence_labels):
            if not lab:
                raise RecordingError(f"sequence_labels[{i}]: empty label")
            bad = [c for c in lab if unicodedata.category(c) in ("Cc", "Cs")]
            if bad:
                raise RecordingError(f"sequence_labels[{i}]: label {lab!r} contains control character {bad[0]!r}")
            if lab in seen:
                raise RecordingError(f"sequence_labels: duplicate label {lab!r} at sequences {seen[lab]} and {i}")
            seen[lab] = i

    def _check_time(self) -> None:
        t = self.time
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            raise NonFiniteValueError(f"time: non-finite value {t[bad[0]]} at time index {bad[0]}")
        d = np.diff(t)
        bad = np.flatnonzero(d <= 0)
        if bad.size:
            k = bad[0] + 1
            raise TimeAxisError(
                f"time: not strictly increasing at time index {k}: time[{k}] = {float(t[k])!r} s "
                f"≤ time[{k - 1}] = {float(t[k - 1])!r} s")
        step = float(np.median(d))
        # The second term only matters for huge absolute times (e.g. Unix epochs), where float64
        # cannot represent a grid that is uniform to TIME_RELATIVE_TOLERANCE · dt.
        tol = TIME_RELATIVE_TOLERANCE * step + 4 * float(np.spacing(np.abs(t).max()))
        bad = np.flatnonzero(np.abs(d - step) > tol)
        if bad.size:
            k = bad[0] + 1
            raise TimeAxisError(
                f"time: non-uniform spacing at time index {k}: time[{k}] - time[{k - 1}] = {float(d[k - 1])!r} s, "
                f"but the typical spacing is dt = {step!r} s (relative tolerance {TIME_RELATIVE_TOLERANCE:g}); "
                f"{bad.size} intervals differ in total")
        lo, hi = SAMPLE_PERIOD_RANGE
        if not lo * (1 - 1e-9) <= step <= hi * (1 + 1e-9):
            guess = "milliseconds" if 1e-3 * step <= hi and step > hi else "another unit"
            raise TimeAxisError(
                f"time: sample period dt = {step:g} s is outside the plausible range [{lo:g}, {hi:g}] s; "
                f"time must be in seconds — is it in {guess}? (the range is "
                f"adadex.data.recording.SAMPLE_PERIOD_RANGE)")

    def _check_finite(self, name: str, arr: np.ndarray) -> None:
        bad = ~np.isfinite(arr)
        if bad.any():
            s, k, j = (int(i) for i in np.argwhere(bad)[0])
            raise NonFiniteValueError(
                f"{name}: non-finite value {arr[s, k, j]} in {self._where(s)} at time index {k} "
                f"(t={self.time[k]:g} s), joint {self.joint_names[j]!r}; "
                f"{int(bad.sum())} non-finite values in total")

    def _check_limits(self) -> None:
        lim = (joint_limits() if self.robot is None else self.robot.limits)[self.joint_indices]
        lo, hi = lim[:, 0], lim[:, 1]
        below = self.command < lo - LIMIT_TOLERANCE
        above = self.command > hi + LIMIT_TOLERANCE
        outside = below | above
        if not outside.any():
            return
        s, k, j = (int(i) for i in np.argwhere(outside)[0])
        value = float(self.command[s, k, j])
        if above[s, k, j]:
            side, limit = "above the joint's upper", float(hi[j])
        else:
            side, limit = "below the joint's lower", float(lo[j])
        raise CommandLimitError(
            f"command: {value!r} rad for joint {self.joint_names[j]!r} in {self._where(s)} at time index {k} "
            f"(t={self.time[k]:g} s) is {side} limit {limit!r} rad (tolerance {LIMIT_TOLERANCE:g} rad); "
            f"{int(outside.sum())} command values are outside the limits in total")

    def check_measured_range(self) -> Recording:
        """``self`` if every measured position lies within the joint limits widened by
        :data:`MEASURED_RANGE_MARGIN`; a :class:`MeasurementRangeError` naming the first one outside
        (sequence, time index, joint) otherwise. Not part of :meth:`validate` — a recording may hold any
        finite measurement — but what the workbench (``adadex sysid``) checks before comparing a model
        with it: errors of 1e6 rad overflow its statistics."""
        lim = (joint_limits() if self.robot is None else self.robot.limits)[self.joint_indices]
        lo, hi = lim[:, 0] - MEASURED_RANGE_MARGIN, lim[:, 1] + MEASURED_RANGE_MARGIN
        outside = (self.joint_pos < lo) | (self.joint_pos > hi)
        if not outside.any():
            return self
        s, k, j = (int(i) for i in np.argwhere(outside)[0])
        raise MeasurementRangeError(
            f"joint_pos: {float(self.joint_pos[s, k, j]):g} rad measured for joint {self.joint_names[j]!r} in "
            f"{self._where(s)} at time index {k} (t={self.time[k]:g} s) is outside the physical range "
            f"[{lo[j]:g}, {hi[j]:g}] rad (the joint limits ± {MEASURED_RANGE_MARGIN:g}); is it in degrees or "
            f"encoder counts? {int(outside.sum())} measured values are outside it in total")

    def _check_finite_qpos(self) -> None:
        bad = ~np.isfinite(self.initial_qpos)
        if bad.any():
            s, j = (int(i) for i in np.argwhere(bad)[0])
            raise NonFiniteValueError(
                f"initial_qpos: non-finite value {self.initial_qpos[s, j]} in {self._where(s)} "
                f"for joint {self._all_joints[j]!r}")

    def _check_qpos_limits(self) -> None:
        """The simulator starts each sequence at ``initial_qpos``: outside the limits it is unstable."""
        lim = joint_limits() if self.robot is None else self.robot.limits
        over = np.maximum(lim[:, 0] - self.initial_qpos, self.initial_qpos - lim[:, 1]) > INITIAL_QPOS_TOLERANCE
        # A recorded joint may start where it was measured (measurements are not limit-checked).
        idx = self.joint_indices
        over[:, idx] &= self.initial_qpos[:, idx] != self.joint_pos[:, 0, :]
        if over.any():
            s, j = (int(i) for i in np.argwhere(over)[0])
            raise CommandLimitError(
                f"initial_qpos: {float(self.initial_qpos[s, j])!r} rad for joint {self._all_joints[j]!r} in "
                f"{self._where(s)} is outside the joint's limits [{lim[j, 0]:g}, {lim[j, 1]:g}] rad "
                f"(tolerance {INITIAL_QPOS_TOLERANCE:g} rad); the simulator cannot start there")

    # ------------------------------------------------------------------ views

    @property
    def num_sequences(self) -> int:
        return int(self.command.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.command.shape[1])

    @property
    def num_joints(self) -> int:
        return int(self.command.shape[2])

    @property
    def dt(self) -> float:
        """Sample period, s: the mean spacing of ``time`` (uniform to 1e-6·dt by validation)."""
        return float((self.time[-1] - self.time[0]) / (self.num_steps - 1))

    @property
    def duration(self) -> float:
        """``time[-1] - time[0]``, s."""
        return float(self.time[-1] - self.time[0])

    @property
    def joint_indices(self) -> np.ndarray:
        """(J,) int64 indices of ``joint_names`` into :data:`~adadex.sim.robot.JOINT_NAMES` (or the
        user model's joint table)."""
        return joint_index(self.joint_names) if self.robot is None else self.robot.index(self.joint_names)

    def full_command(self) -> np.ndarray:
        """(S, T, 22) commands for every joint, in JOINT_NAMES (or the model's table) order: what the
        simulator is sent.

        Recorded joints get ``command``; the others are held at ``initial_qpos`` throughout.
        """
        out = np.repeat(self.initial_qpos[:, None, :], self.num_steps, axis=1)
        out[:, :, self.joint_indices] = self.command
        return out

    def subset(self, sequences=None, joints=None) -> Recording:
        """A new recording with some sequences and/or joints, in the order given.

        ``sequences``: an index, a label, or a list of them (negative indices count from the end);
        ``None`` keeps all. ``joints``: a joint name or a list of recorded joint names; ``None``
        keeps all. ``initial_qpos`` keeps all 22 joints, so a dropped joint is held at its initial
        value by :meth:`full_command`. If ``meta["sequences"]`` is a per-sequence list (as
        written by :mod:`adadex.sysid.excite`), it is subset along with the sequences.
        """
        s_idx = self._select_sequences(sequences)
        j_idx = self._select_joints(joints)
        pick = np.ix_(s_idx, np.arange(self.num_steps), j_idx)
        meta = json.loads(json.dumps(self.meta))
        per_seq = meta.get("sequences")
        if isinstance(per_seq, list) and len(per_seq) == self.num_sequences:
            meta["sequences"] = [per_seq[i] for i in s_idx]
        return Recording(
            time=self.time,
            joint_names=tuple(self.joint_names[j] for j in j_idx),
            command=self.command[pick],
            joint_pos=self.joint_pos[pick],
            joint_vel=None if self.joint_vel is None else self.joint_vel[pick],
            sequence_labels=tuple(self.sequence_labels[i] for i in s_idx),
            initial_qpos=self.initial_qpos[s_idx],
            meta=meta,
            robot=self.robot,
        )

    def _select_sequences(self, sequences) -> np.ndarray:
        S = self.num_sequences
        if sequences is None:
            return np.arange(S)
        if isinstance(sequences, (str, int, np.integer)):
            sequences = [sequences]
        out: list[int] = []
        for item in sequences:
            if isinstance(item, (bool, np.bool_)):
                raise RecordingError(f"sequences: expected a sequence index or label, got {item!r}")
            if isinstance(item, (int, np.integer)):
                if not -S <= item < S:
                    raise RecordingError(f"sequences: index {item} is out of range for {S} sequences")
                i = int(item) % S
            elif isinstance(item, str):
                if item not in self.sequence_labels:
                    close = difflib.get_close_matches(item, self.sequence_labels, n=3)
                    hint = f"; did you mean {', '.join(map(repr, close))}?" if close else ""
                    raise RecordingError(f"sequences: no sequence labelled {item!r}{hint}")
                i = self.sequence_labels.index(item)
            else:
                raise RecordingError(f"sequences: expected a sequence index or label, got {type(item).__name__}")
            if i in out:
                raise RecordingError(f"sequences: {self._where(i)} is selected twice")
            out.append(i)
        if not out:
            raise RecordingError("sequences: empty selection; a recording needs at least 1 sequence")
        return np.asarray(out, dtype=np.int64)

    def _select_joints(self, joints) -> np.ndarray:
        if joints is None:
            return np.arange(self.num_joints)
        names = _str_tuple([joints] if isinstance(joints, str) else joints, "joints", JointNameError)
        out: list[int] = []
        for n in names:
            if n not in self._all_joints:
                raise self._unknown(n, "joints")
            if n not in self.joint_names:
                raise JointNameError(f"joints: {n!r} is not recorded (recorded joints: {', '.join(self.joint_names)})")
            j = self.joint_names.index(n)
            if j in out:
                raise JointNameError(f"joints: {n!r} is selected twice")
            out.append(j)
        if not out:
            raise JointNameError("joints: empty selection; a recording needs at least 1 joint")
        return np.asarray(out, dtype=np.int64)

    def __eq__(self, other) -> bool:
        if not isinstance(other, Recording):
            return NotImplemented
        if any(getattr(self, n) != getattr(other, n) for n in ("joint_names", "sequence_labels", "meta")):
            return False
        if (self.joint_vel is None) != (other.joint_vel is None):
            return False
        return all(np.array_equal(getattr(self, n), getattr(other, n))
                   for n in ("time", "command", "joint_pos", "joint_vel", "initial_qpos")
                   if getattr(self, n) is not None)

    __hash__ = None

    def __repr__(self) -> str:
        return (f"Recording({self.num_sequences} sequences × {self.num_steps} steps, dt={self.dt:g} s, "
                f"joints={list(self.joint_names)}, joint_vel={'yes' if self.joint_vel is not None else 'no'}, "
                f"labels={list(self.sequence_labels[:3])}{'…' if self.num_sequences > 3 else ''}, "
                f"meta keys={sorted(self.meta)})")

    # ------------------------------------------------------------------ files

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The ``.npz`` contents: float64 arrays, numpy unicode strings, ``meta`` as a JSON string."""
        out = {
            "time": self.time,
            "joint_names": np.array(self.joint_names, dtype=str),
            "command": self.command,
            "joint_pos": self.joint_pos,
            "sequence_labels": np.array(self.sequence_labels, dtype=str),
            "initial_qpos": self.initial_qpos,
            "meta": np.array(json.dumps(self.meta)),
        }
        if self.joint_vel is not None:
            out["joint_vel"] = self.joint_vel
        return out

    def save(self, path) -> Path:
        """Write the recording to ``path`` as ``.npz``, atomically; returns the path.

        The data is validated first and written to a temporary file in the same directory that
        replaces ``path`` only when complete, so ``path`` is never partially written and bad data
        writes nothing. Parent directories are created.
        """
        path = Path(path)
        if path.suffix.lower() == ".csv":
            raise RecordingFileError(f"{path}: save writes .npz; use to_csv(recording, directory) for CSV")
        self.validate()
        arrays = self.to_arrays()
        atomic_write(path, lambda f: np.savez(f, **arrays))
        return path

    @classmethod
    def load(cls, path, *, robot=None) -> Recording:
        """Read and validate an ``.npz`` recording (of ``robot``'s model, default adadex's); errors
        name the file (and the key)."""
        path = Path(path)
        try:
            archive = np.load(path, allow_pickle=False)
        except (FileNotFoundError, IsADirectoryError, PermissionError):
            raise
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise RecordingFileError(f"{path}: not a readable .npz recording ({e})") from None
        if not isinstance(archive, np.lib.npyio.NpzFile):
            raise RecordingFileError(f"{path}: not a .npz archive (a single .npy array?); a recording is an .npz")
        with archive:
            keys = set(archive.files)
            missing = [k for k in REQUIRED_KEYS if k not in keys]
            if missing:
                raise RecordingFileError(
                    f"{path}: missing required key {missing[0]!r} (a recording needs {', '.join(REQUIRED_KEYS)}; "
                    f"the file has {', '.join(sorted(keys)) or 'no keys'})")
            extra = sorted(keys - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS))
            if extra:
                raise RecordingFileError(
                    f"{path}: unexpected key {extra[0]!r} (allowed: {', '.join(REQUIRED_KEYS + OPTIONAL_KEYS)})")
            fields = {}
            for k in sorted(keys):
                try:
                    fields[k] = archive[k]
                except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:   # truncated archives fail here
                    raise RecordingFileError(f"{path}: key {k!r} cannot be read ({e})") from None
        for k in ("joint_names", "sequence_labels"):
            if k in fields:
                fields[k] = _strings_from_file(fields[k], k, path)
        if "meta" in fields:
            fields["meta"] = _meta_from_file(fields["meta"], path)
        try:
            return cls(**fields, robot=robot)
        except RecordingError as e:
            raise prefixed(e, path) from None


def _strings_from_file(arr: np.ndarray, key: str, path: Path) -> tuple[str, ...]:
    if arr.ndim != 1 or arr.dtype.kind not in "US":
        raise RecordingFileError(
            f"{path}: key {key!r} must be a 1-D string array, got {arr.dtype} of shape {arr.shape}")
    if arr.dtype.kind == "S":
        return tuple(b.decode("utf-8") for b in arr.tolist())
    return tuple(arr.tolist())


def _meta_from_file(arr: np.ndarray, path: Path) -> dict:
    if arr.ndim != 0 or arr.dtype.kind not in "US":
        raise RecordingFileError(f"{path}: key 'meta' must be a JSON string, got {arr.dtype} of shape {arr.shape}")
    text = arr.item()
    text = text.decode("utf-8") if isinstance(text, bytes) else text
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as e:
        raise RecordingFileError(f"{path}: key 'meta' is not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise RecordingFileError(f"{path}: key 'meta' must be a JSON object, got {type(meta).__name__}")
    return meta


# ---------------------------------------------------------------------- loading by extension


def load_recording(path, *, robot=None) -> Recording:
    """Load a recording: ``.csv`` file or a directory of them via :func:`from_csv`, else ``.npz``.

    Args:
        path: a ``.csv`` file, a folder of them (one per sequence), or an ``.npz`` file.
        robot: the joint table of the user's model the recording was made on (None: adadex's).

    Returns:
        the validated :class:`Recording`.
    """
    path = Path(path)
    if path.is_dir() or path.suffix.lower() == ".csv":
        rec = from_csv(path) if robot is None else recording_csv.read_csv(
            functools.partial(Recording, robot=robot), path, None)
        return rec
    return Recording.load(path, robot=robot)


# ---------------------------------------------------------------------- CSV


def from_csv(paths, label=None) -> Recording:
    """Read a recording from CSV files, one sequence per file (see :mod:`adadex.data.recording_csv`).

    ``paths``: a file, a list of files (sequence order), or a directory (all ``*.csv`` in natural
    name order). ``label``: a label, or a list with one per file; default: each file's name
    without ``.csv``, percent-decoded (as written by :func:`to_csv`). Every file must have the
    same joints (in any column order; the first file's order is used) and an identical ``time``
    column. Errors name the file; nothing is returned unless every file is valid.
    """
    return recording_csv.read_csv(Recording, paths, label)


def to_csv(rec: Recording, directory) -> list[Path]:
    """Write one CSV file per sequence into ``directory`` (created); returns the paths in order.

    Everything is validated and rendered before anything is written; each file is written to a
    temporary file and renamed into place, so no file is ever partial. ``initial_qpos`` and
    ``meta`` are not written (see :mod:`adadex.data.recording_csv`).
    """
    if not isinstance(rec, Recording):
        raise ConfigTypeError(f"to_csv: expected a Recording, got {type(rec).__name__}")
    return recording_csv.write_csv(rec, directory)
