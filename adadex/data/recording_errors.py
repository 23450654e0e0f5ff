"""The errors of the recording format (:mod:`adadex.data.recording`), in a module of their own so
that the format's readers and writers (:mod:`adadex.data.recording_csv`) raise the same types
without importing the :class:`~adadex.data.recording.Recording` module. Import them from
:mod:`adadex.data.recording`, which re-exports them.
"""

from __future__ import annotations

from adadex.errors import AdadexError
from adadex.sim.robot import UnknownJointError


class RecordingError(AdadexError, ValueError):
    """Invalid recording data; the message says what is wrong and where."""


class RecordingShapeError(RecordingError):
    """An array has the wrong number of dimensions or the wrong size (expected vs got)."""


class NonFiniteValueError(RecordingError):
    """NaN or ±inf in an array."""


class TimeAxisError(RecordingError):
    """``time`` is too short, not strictly increasing, or not uniformly spaced."""


class JointNameError(RecordingError):
    """A joint name is missing, duplicated, not a string, or not recorded."""


class UnknownJointNameError(JointNameError, UnknownJointError):
    """A joint name that is not one of the robot's JOINT_NAMES (also a ``robot.UnknownJointError``)."""

    def __init__(self, message: str):
        Exception.__init__(self, message)

    def __str__(self) -> str:
        return str(self.args[0])


class CommandLimitError(RecordingError):
    """A command lies outside its joint's position limits."""


class MeasurementRangeError(RecordingError):
    """A measured position lies so far outside its joint's limits that it cannot be a reading of the joint."""


class RecordingFileError(RecordingError):
    """A file that cannot be read as a recording: not an archive, missing or unexpected keys, bad CSV."""


def prefixed(exc: RecordingError, where) -> RecordingError:
    """The same error type with ``where`` (a file, usually) prefixed to its message."""
    return type(exc)(f"{where}: {exc}")


def unknown_joint(name, where: str) -> UnknownJointNameError:
    """The error for a joint name that is not one of JOINT_NAMES, found at ``where``."""
    return UnknownJointNameError(f"{where}: {UnknownJointError(name).args[0]}")
