"""Where the files adadex ships live: the robot's MJCF, the trained point-cloud encoder, the demo
recording.

They sit in the checkout's top-level ``assets/`` folder, which the package reaches through the
``adadex/assets`` link and the wheel carries as package data, so the same call finds them in a
checkout, an editable install and an installed wheel:

>>> from adadex.resources import asset
>>> asset("robot", "robot.xml").name
'robot.xml'
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def asset(*parts: str) -> Path:
    """Path of a shipped file under ``assets/`` (e.g. ``asset("encoder", "encoder.pt")``)."""
    return Path(str(files("adadex").joinpath("assets", *parts)))
