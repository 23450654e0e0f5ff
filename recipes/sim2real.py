"""The sim-to-real loop in one command — see sim2real.yaml and adadex/train/sim2real.py.

    python recipes/sim2real.py real=assets/gaps/weak_shoulder.json out=runs/s2r preset=small
    python recipes/sim2real.py real=PATCH.json out=DIR [tracker=PATH] [preset=tiny|small] [seed=…]

Treats ``real`` as a hidden robot: records on it (``adadex sysid excite`` + ``simulate``, with sensor
noise) and evaluates on it, never reading its patch otherwise; identifies it (``adadex sysid diagnose`` →
``fit --accept``), trains modulators around the frozen tracker under Table 3 and around the identified
model (``Randomization.from_patch``), and evaluates every row on the same draws. Writes
``out/sim2real.json`` (rows with bootstrap intervals, the gap, the recovered fraction, the diagnosis,
minutes per stage) and ``out/sim2real.png``, and prints the table.

The settings are ``key=value`` pairs over sim2real.yaml, as in the other recipes, read with OmegaConf
rather than Hydra: ``preset=`` names this loop's sizes, and under Hydra it would select the pipeline's
``recipes/preset/`` config group instead. Unknown keys are refused (one line naming the known ones).

An ``out`` holding anything but an earlier sim2real output is refused before any work (``force=true``
writes into it). Bad input (a ``real`` that is not a model patch, a missing tracker or dataset, an
unknown key or preset) is one line on stderr and exit code 2.
"""

from __future__ import annotations

import sys
from pathlib import Path

from omegaconf import OmegaConf

from adadex.errors import ConfigError, exit_on_error
from adadex.train.recipe import check_keys, check_overrides, yaml_keys

CONFIG = Path(__file__).with_name("sim2real.yaml")


def keys() -> dict:
    """What the recipe accepts: sim2real.yaml's keys and every :class:`Sim2RealPreset` field (a change to
    the preset's value; ``reward.*``: :class:`RewardConfig` fields; ``modulation.*``: :class:`ModulationConfig`
    fields)."""
    from adadex.train.config_store import keys as node_keys
    from adadex.train.sim2real import PRESET_FIELDS

    return yaml_keys(CONFIG, **{k: None for k in PRESET_FIELDS if k not in ("dataset", "reward", "modulation")},
                     reward=node_keys("adadex_reward"), modulation=node_keys("adadex_modulation"))


def preset_changes(cfg) -> dict:
    """The :class:`Sim2RealPreset` fields the command line set (lists as tuples)."""
    from adadex.train.sim2real import PRESET_FIELDS

    c = OmegaConf.to_container(cfg, resolve=True)
    return {k: tuple(c[k]) if isinstance(c[k], list) else c[k] for k in PRESET_FIELDS if k in c and k != "dataset"}


def config(argv: list[str]):
    """sim2real.yaml with the ``key=value`` settings of ``argv``; unknown keys and missing values refused."""
    bad = [a for a in argv if "=" not in a or a.startswith(("-", "+", "~"))]
    if bad:
        raise ConfigError(f"expected key=value settings (e.g. real=assets/gaps/weak_shoulder.json out=DIR), "
                          f"got {bad[0]!r}")
    check_overrides(argv, keys())
    cfg = OmegaConf.merge(OmegaConf.load(CONFIG), OmegaConf.from_dotlist(argv))
    cfg.pop("hydra", None)
    check_keys(cfg, keys())
    missing = sorted(k for k in ("real", "out") if OmegaConf.is_missing(cfg, k))
    if missing:
        raise ConfigError(f"{' and '.join(f'{k}=' for k in missing)} must be given "
                          f"(e.g. real=assets/gaps/weak_shoulder.json out=runs/s2r)")
    return cfg


def guard(cfg) -> None:
    """What is checked before any work: the preset, the hidden robot, the tracker, then ``out``."""
    from adadex.train.sim2real import HiddenRobot, check_out, preset

    preset(str(cfg.preset), **preset_changes(cfg))
    HiddenRobot(cfg.real)
    if str(cfg.tracker) != "replay" and not Path(str(cfg.tracker)).is_file():
        raise FileNotFoundError(f"tracker={cfg.tracker}: no such checkpoint file")
    check_out(cfg.out, force=bool(cfg.force))


def main(argv: list[str] | None = None) -> dict:
    from adadex.train.sim2real import format_table, run_sim2real

    with exit_on_error("recipes/sim2real.py"):
        cfg = config(sys.argv[1:] if argv is None else argv)
        guard(cfg)
        result = run_sim2real(str(cfg.real), str(cfg.out), tracker=str(cfg.tracker), preset_name=str(cfg.preset),
                              seed=int(cfg.seed), dataset=cfg.dataset, oracle=bool(cfg.oracle), force=bool(cfg.force),
                              progress=bool(cfg.progress), threads=int(cfg.threads), **preset_changes(cfg))
    print()
    print(format_table(result))
    print(f"minutes per stage: {result['stage_minutes']}")
    print(f"wrote {cfg.out}/sim2real.json and sim2real.png")
    return result


if __name__ == "__main__":
    main()
