"""The dataset presets of ``adadex data build`` (:data:`PRESETS`; documented in :mod:`adadex.data.build`),
apart from the builder so that the command's help lists them without importing torch."""

from __future__ import annotations

from dataclasses import dataclass

from adadex.sim.objects import OBJECT_NAMES, held_out_objects


@dataclass(frozen=True)
class Preset:
    """How many references to build, on which objects."""

    name: str
    objects: tuple[str, ...]
    base_instructions: int
    paraphrases: int
    description: str


def _paper_objects() -> tuple[str, ...]:
    held = set(held_out_objects())
    seen = [n for n in OBJECT_NAMES if n not in held]
    step = len(seen) / 45
    return tuple(seen[int(i * step)] for i in range(45)) + tuple(sorted(held))


#: The presets of ``adadex data build``, by name: ``tiny``, ``small``, ``paper``.
PRESETS: dict[str, Preset] = {
    "tiny": Preset("tiny", ("cube_050", "cylinder_02", "bottle_00", "box_04"), 4, 2,
                   "8 references on 4 objects (box_04 held out); for tests"),
    "small": Preset("small", OBJECT_NAMES, 100, 4, "≈400 references over all 80 objects; for CPU experiments"),
    "paper": Preset("paper", _paper_objects(), 505, 10, "505 base × 10 paraphrases over 50 objects (paper size)"),
}
