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


class ArrayError(AdadexError, ValueError):
    """An input array (an action, say) has the wrong shape or non-finite values."""


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
    """Return ``value`` (a numpy array) if it has ``shape`` and only finite values; raise
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
