"""The one root of adadex's exceptions, and the one check of a config number.

Every exception adadex raises on bad input derives from :class:`AdadexError`, so a caller (the CLI,
a recipe, a user's script) can catch the library's input errors in one ``except`` and let bugs
through. Classes that describe bad values also subclass ``ValueError`` (or ``KeyError`` for unknown
names), so code written against the built-in types keeps working.

>>> from adadex.errors import AdadexError, ConfigError, check_number
>>> check_number("RewardConfig.w_alive", 0.5)
0.5
>>> try:
...     check_number("RewardConfig.w_alive", float("nan"))
... except ConfigError as e:
...     print(e)
RewardConfig.w_alive must be a finite number ≥ 0, got nan
>>> issubclass(ConfigError, (AdadexError, ValueError))
True
"""

from __future__ import annotations

import math
from numbers import Real


class AdadexError(Exception):
    """Root of every exception adadex raises for bad input or a failed operation it can explain."""


class ConfigError(AdadexError, ValueError):
    """A configuration value is out of range or of the wrong type."""


class CheckpointError(AdadexError, ValueError):
    """A checkpoint that cannot be read, is of another kind, or does not belong to this run."""


class ArrayError(AdadexError, ValueError):
    """An input array (an action, say) has the wrong shape or non-finite values."""


class UnknownKeyError(AdadexError, KeyError):
    """A name or entry the caller gave is unknown, or an input (a tensordict, a dict) lacks one it needs."""


class ConfigTypeError(AdadexError, TypeError):
    """A setting or argument is of the wrong kind (an object where another is expected)."""


def check_number(name: str, value, *, low: float = 0.0, high: float = math.inf, integer: bool = False,
                 strict_low: bool = False):
    """Return ``value`` if it is a finite real number in ``[low, high]`` (``(low, high]`` with
    ``strict_low``), an integer when ``integer``; raise :class:`ConfigError` naming ``name`` otherwise.

    Booleans are refused: ``True`` as a weight is a typo, not a number.
    """
    ok = isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)
    if ok and integer:
        ok = float(value).is_integer()
    if ok:
        ok = (value > low if strict_low else value >= low) and value <= high
    if not ok:
        kind = "an integer" if integer else "a finite number"
        if low == 0 and high == math.inf:
            bound = "> 0" if strict_low else "≥ 0"
        elif high == math.inf:
            bound = f"> {low:g}" if strict_low else f"≥ {low:g}"
        else:
            bound = f"in {'(' if strict_low else '['}{low:g}, {high:g}]"
        raise ConfigError(f"{name} must be {kind} {bound}, got {value!r}")
    return value


def check_numbers(owner: str, obj, names) -> None:
    """:func:`check_number` on ``obj.<name>`` for each name, errors naming ``owner.<name>``."""
    for k in names:
        check_number(f"{owner}.{k}", getattr(obj, k))


def check_array(name: str, value, shape: tuple[int, ...]):
    """Return ``value`` (a numpy array or a torch tensor) if it has ``shape`` and only finite values; raise
    :class:`ArrayError` naming ``name``, the expected and the actual shape, or the first bad index.

    >>> import numpy as np
    >>> check_array("action", np.zeros((2, 3)), (2, 3)).shape
    (2, 3)
    >>> check_array("action", np.zeros((2, 4)), (2, 3))
    Traceback (most recent call last):
    ...
    adadex.errors.ArrayError: action: expected shape (2, 3), got (2, 4)
    """
    import numpy as np

    got = tuple(getattr(value, "shape", ()))
    if got != tuple(shape):
        raise ArrayError(f"{name}: expected shape {tuple(shape)}, got {got}")
    if hasattr(value, "isfinite"):            # a torch tensor, on any device: one read back
        if bool(value.isfinite().all()):
            return value
        value = value.detach().cpu().numpy()
    bad = ~np.isfinite(value)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ArrayError(f"{name}: non-finite value {value[idx]} at index {idx}")
    return value


def from_known_keys(cls, d: dict):
    """``cls(**d)`` for a dataclass ``cls``, refusing keys it does not have with one :class:`ConfigError`
    naming them all (a typo in a config file is an error, not a silently ignored setting)."""
    import dataclasses

    unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise ConfigError(f"{cls.__name__}: unknown keys {unknown}")
    return cls(**d)


# ----------------------------------------------------------------------------------------------
# The one error contract of the ``adadex`` command and the recipes

#: built-in exceptions that mean bad input too: a path given that is missing, a folder where a file is
#: expected, a file that may not be read or replaced
INPUT_ERRORS = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, FileExistsError)


def one_line(error: BaseException) -> str:
    """``error``'s message on one line (a ``KeyError``'s without the quotes ``str`` adds)."""
    msg = str(error.args[0]) if isinstance(error, KeyError) and error.args else str(error)
    return " ".join(part.strip() for part in msg.splitlines() if part.strip()) or type(error).__name__


def report_error(prog: str, error: BaseException, *, hint: str = "", traceback: bool = False) -> int:
    """Report ``error`` from the command ``prog`` on stderr; return the exit code.

    Bad input — an :class:`AdadexError` or one of :data:`INPUT_ERRORS` — is one line,
    ``prog: error: …``, exit code 2. Anything else is a bug in adadex: ``prog: internal error (a bug
    in adadex, please report it): Type: …`` (``hint`` appended, e.g. how to see the traceback; with
    ``traceback`` the traceback is printed above it), exit code 1.

    >>> import contextlib, io
    >>> err = io.StringIO()
    >>> with contextlib.redirect_stderr(err):
    ...     report_error("adadex x", ConfigError("a.b must be > 0, got -1"))
    2
    >>> err.getvalue()
    'adadex x: error: a.b must be > 0, got -1\\n'
    """
    import sys

    if isinstance(error, (AdadexError, *INPUT_ERRORS)):
        print(f"{prog}: error: {one_line(error)}", file=sys.stderr)
        return 2
    if traceback:
        import traceback as tb

        tb.print_exception(error, file=sys.stderr)
    print(f"{prog}: internal error (a bug in adadex, please report it): {type(error).__name__}: {one_line(error)}"
          f"{hint}", file=sys.stderr)
    return 1


def exit_on_error(prog: str, *, traceback: bool = True):
    """A context manager: an exception leaving the block is reported by :func:`report_error` and the
    process exits with its code (2: bad input, one line; 1: a bug). What the recipes run in.
    ``KeyboardInterrupt`` and ``SystemExit`` pass through."""
    import contextlib
    import sys

    @contextlib.contextmanager
    def guard():
        try:
            yield
        except Exception as e:      # noqa: BLE001 - this is the one place errors are turned into exit codes
            sys.exit(report_error(prog, e, traceback=traceback))

    return guard()
