"""From a Hydra recipe's config (``recipes/*.yaml``) to a run: strict keys, the output guard, one error contract.

The recipes stay thin: their keys are the config dataclasses' fields (the ConfigStore nodes of
:mod:`adadex.train.config_store`, which :func:`recipe_main` registers), so a composed PPO recipe config *is*
a :class:`TrainConfig` plus the recipe's ``force`` and ``build_preset`` (:func:`train_settings`);
:func:`run` builds the dataset if asked and trains.

Every recipe runs through :func:`recipe_main`, which checks the command line *before Hydra starts*
(Hydra makes the run folder ``out`` and writes its ``.hydra/`` and log there before the recipe's code
runs):

* **strict keys** — a setting the recipe does not know (``+foo=1``, ``ppo.foo=1``, ``+ppo.foo=1``,
  ``+preset=tiny`` on a training recipe) is refused with one line naming it and the known ones. What
  is known comes from the config dataclasses (:func:`adadex.train.config_store.keys`; :func:`dataclass_keys`
  for a flat one), not from a second list kept by hand;
* **the output guard** — the recipe's ``guard`` (for a training run :func:`check_training_out`; for
  ``evaluate.py`` and ``train_encoder.py`` :func:`check_recipe_out`) on the composed config, so a user's
  folder, a finished run without ``resume=true``, a resume without a checkpoint or with other settings
  are refused before anything is written.

The same checks run again inside the recipe (for ``-m`` multiruns, whose composed configs exist only
there). Errors follow the one contract of :func:`adadex.errors.report_error`: bad input is one line
and exit code 2, anything else is a bug, exit code 1.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import sys
from collections.abc import Callable, Mapping
from pathlib import Path

from omegaconf import OmegaConf

from adadex.errors import ConfigError, exit_on_error
from adadex.train.config import TrainConfig

#: the PPO recipes' own keys beside TrainConfig's fields
RECIPE_OPTIONS = ("force", "build_preset")


# ----------------------------------------------------------------------------------------------
# Strict keys

def dataclass_keys(cls, *, drop=(), **nested) -> dict:
    """The keys a config dataclass accepts, as a key schema: ``{field: None}`` (a value, or a mapping
    whose keys are checked where it is used), with ``nested`` schemas for fields that hold another
    config (``ppo=dataclass_keys(PPOConfig)``); fields in ``drop`` left out."""
    keys = {f.name: None for f in dataclasses.fields(cls) if f.name not in drop}
    return {**keys, **nested}


def modulation_keys() -> dict:
    """:class:`~adadex.modules.channels.ModulationConfig`'s fields (the ``modulation`` settings)."""
    from adadex.modules.channels import ModulationConfig

    return dataclass_keys(ModulationConfig)


def yaml_keys(path, **nested) -> dict:
    """A recipe file's own top-level keys (``defaults`` and ``hydra`` aside) as a key schema, for recipes
    whose settings are not a config dataclass."""
    cfg = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    return {**{k: None for k in cfg if k not in ("defaults", "hydra")}, **nested}


def train_keys() -> dict:
    """What the PPO recipes (``train_common.yaml`` and the recipes on it) accept: :class:`TrainConfig`'s
    fields, every field of the configs nested in it (``ppo``, ``collector``, ``sim``, ``policy``,
    ``modulator`` with ``modulation``, ``env``, ``reward``, ``randomization``) and :data:`RECIPE_OPTIONS`
    — the ``adadex_train`` node's keys."""
    from adadex.train.config_store import keys

    return keys("adadex_train")


def _unknown(d: Mapping, schema: dict, prefix: str = "") -> list[tuple[str, str, list[str]]]:
    """(dotted name, parent, known keys there) for each key of ``d`` the ``schema`` does not have."""
    found = []
    for k, v in d.items():
        if k not in schema:
            found.append((f"{prefix}{k}", prefix[:-1], sorted(schema)))
        elif isinstance(schema[k], dict) and isinstance(v, Mapping):
            found += _unknown(v, schema[k], f"{prefix}{k}.")
    return found


def _refuse_unknown(found: list[tuple[str, str, list[str]]]) -> None:
    if not found:
        return
    parts = []
    for parent in dict.fromkeys(p for _, p, _ in found):
        names = [n for n, p, _ in found if p == parent]
        known = next(k for _, p, k in found if p == parent)
        where = f"known under {parent}" if parent else "known"
        parts.append(f"unknown setting{'s' if len(names) > 1 else ''} {', '.join(repr(n) for n in names)} "
                     f"({where}: {', '.join(known)})")
    raise ConfigError("; ".join(parts))


def check_keys(cfg, schema: dict) -> None:
    """Refuse, with one :class:`ConfigError` naming them and the known keys, the keys of the composed
    config ``cfg`` (a mapping or a ``DictConfig``) that ``schema`` does not have."""
    if OmegaConf.is_config(cfg):
        cfg = OmegaConf.to_container(cfg, resolve=False)
    _refuse_unknown(_unknown(cfg, schema))


def check_overrides(overrides: list[str], schema: dict) -> None:
    """:func:`check_keys` for Hydra command-line overrides (``key=value``, ``+key=value``, ``~key``);
    ``hydra.*`` and unparsable overrides are left to Hydra."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
    except Exception:            # noqa: BLE001 - Hydra itself reports a malformed override
        return
    found = []
    for o in parsed:
        key = o.key_or_group
        if key == "hydra" or key.startswith(("hydra.", "hydra/")):
            continue
        level, prefix = schema, ""
        for part in key.split("."):
            if part not in level:
                found.append((f"{prefix}{part}", prefix[:-1], sorted(level)))
                break
            if not isinstance(level[part], dict):
                break
            level, prefix = level[part], f"{prefix}{part}."
    _refuse_unknown(list({f[0]: f for f in found}.values()))


# ----------------------------------------------------------------------------------------------
# Running a recipe

def _compose(config_dir: Path, config_name: str, argv: list[str], schema: dict):
    """The config Hydra will compose for ``argv`` (after :func:`check_overrides`), or ``None`` where the
    command line asks for something else (``-m``, ``--cfg``, ``--help`` …) or Hydra will refuse it
    itself."""
    from hydra._internal.utils import get_args_parser

    with contextlib.redirect_stderr(io.StringIO()):
        try:
            args = get_args_parser().parse_args(argv)
        except SystemExit:
            return None
    check_overrides(args.overrides, schema)
    if (args.multirun or args.cfg or args.help or args.hydra_help or args.info or args.shell_completion
            or args.experimental_rerun or args.config_path or args.config_name or args.config_dir):
        return None
    from hydra import compose, initialize_config_dir

    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            return compose(config_name=config_name, overrides=list(args.overrides))
    except Exception:            # noqa: BLE001 - a composition error: Hydra reports it when it runs
        return None


def recipe_main(main: Callable, *, schema: dict, guard: Callable | None = None, config_name: str | None = None):
    """Run the Hydra recipe ``main`` (a ``@hydra.main`` function) as a command: first, before Hydra makes
    or writes anything, refuse unknown keys (:func:`check_overrides`, then :func:`check_keys` on the
    composed config) and run ``guard(cfg)`` (the output guard) — one line and exit code 2 on bad input —
    then ``main()``. ``config_name`` defaults to the recipe file's name."""
    import inspect

    global _CHECKING_COMMAND_LINE

    from omegaconf.errors import OmegaConfBaseException

    from adadex.train.config_store import register

    register()                       # the config nodes the recipes' defaults lists name
    file = Path(inspect.getfile(getattr(main, "__wrapped__", main)))
    with exit_on_error(f"recipes/{file.name}"):
        cfg = _compose(file.parent, config_name or file.stem, sys.argv[1:], schema)
        if cfg is not None:
            check_keys(cfg, schema)
            if guard is not None:
                _CHECKING_COMMAND_LINE = True
                try:
                    guard(cfg)
                except OmegaConfBaseException:
                    pass             # an interpolation that does not resolve …: Hydra reports it when it runs
                finally:
                    _CHECKING_COMMAND_LINE = False
    return main()


#: True while :func:`recipe_main` checks the command line, before Hydra runs (:func:`hydra_files`)
_CHECKING_COMMAND_LINE = False


# ----------------------------------------------------------------------------------------------
# The PPO recipes

def train_settings(cfg: Mapping) -> tuple[TrainConfig, dict]:
    """A composed PPO recipe config (a mapping or an OmegaConf ``DictConfig``) as the
    :class:`TrainConfig` it holds and the recipe's own options (:data:`RECIPE_OPTIONS`). The keys are
    the fields: nothing is renamed; TrainConfig's checks validate the values.

    >>> tc, options = train_settings({"dataset": "d", "out": "o", "ppo": {"total_frames": 512}, "force": True})
    >>> tc.ppo.total_frames, options
    (512, {'force': True})
    """
    if OmegaConf.is_config(cfg):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    settings = dict(cfg)
    options = {k: settings.pop(k) for k in RECIPE_OPTIONS if k in settings}
    return TrainConfig.from_dict(settings), options


def check_training_out(cfg) -> dict | None:
    """The output guard of a PPO recipe (:func:`adadex.train.checkpoint.check_run`, strict: ``resume=true``
    needs a checkpoint): the checkpoint to continue from, or ``None`` for a fresh run. Writes nothing."""
    from adadex.train.checkpoint import TRAINING_RUN, check_run

    tc, options = train_settings(cfg)
    return check_run(tc.out, TRAINING_RUN, tc.to_dict(), resume=tc.resume, force=bool(options.get("force", False)),
                     ignore=hydra_files(tc.out))


def hydra_files(out) -> tuple[str, ...]:
    """What Hydra itself has put into ``out`` when it is this recipe's run folder (``.hydra/``, the job's
    log), made before the recipe's code runs — after :func:`recipe_main` checked ``out``."""
    if _CHECKING_COMMAND_LINE:
        return ()          # Hydra has not started: whatever is in out is not its
    try:
        from hydra.core.hydra_config import HydraConfig

        if not HydraConfig.initialized():
            return ()
        hc = HydraConfig.get()
        if Path(hc.runtime.output_dir).resolve() != Path(out).resolve():
            return ()
        return tuple(n for n in (hc.output_subdir, f"{hc.job.name}.log") if n)
    except Exception:            # noqa: BLE001 - no Hydra run: nothing of Hydra's to ignore
        return ()


# ----------------------------------------------------------------------------------------------
# Recipes whose out= folder is written as they go (evaluate.py, train_encoder.py)

#: the output kinds of those recipes (the marker in their ``out`` folder, :mod:`adadex.io`)
EVALUATION = "evaluation"
ENCODER_TRAINING = "encoder training run"


def check_recipe_out(cfg, kind: str) -> Path:
    """The output guard of a recipe of ``kind`` whose ``out`` folder is written file by file (``evaluate.py``,
    ``train_encoder.py``), as ``guard`` of :func:`recipe_main` and again inside the recipe: ``out`` absent,
    empty, an earlier output of the same recipe (its marker), or ``force=true``; anything else (someone
    else's files, a file) is refused with one line naming it and ``force=true``
    (:func:`adadex.io.check_output_dir`). Writes nothing; the recipe marks it (:func:`claim_recipe_out`)."""
    from adadex.io import check_output_dir

    out = Path(str(cfg.get("out")))
    return check_output_dir(out, kind, force=bool(cfg.get("force", False)), option="force=true",
                            ignore=hydra_files(out))


def claim_recipe_out(cfg, kind: str) -> Path:
    """:func:`check_recipe_out`, then mark ``out`` as the recipe's output (before its work: a rerun may
    replace it)."""
    from adadex.io import mark_output_dir

    return mark_output_dir(check_recipe_out(cfg, kind), kind)


def run(cfg: Mapping, *, name: str, prog: str | None = None, modulator: bool = False, **trainer) -> dict:
    """Check the keys and the output folder, build the dataset if missing (``build_preset``), train,
    print and return the final evaluation. ``trainer``: :class:`~adadex.train.ppo.PPOTrainer`'s own
    modules — ``policy``, ``loss``, ``env_transforms`` — for a recipe that trains a policy it composed
    (``recipes/train_custom_policy.py``). ``modulator``: the recipe trains a modulator, so
    ``modulator.tracker`` is required (``recipes/train_modulator.py``).

    Bad input — an unknown key, an ``out`` that holds someone else's files or a run not to be replaced,
    a missing dataset or checkpoint, a bad setting, an unknown group — is one line on stderr and exit
    code 2, no traceback; anything else is reported as a bug, exit code 1
    (:func:`adadex.errors.report_error`)."""
    with exit_on_error(prog or f"recipes/{Path(sys.argv[0]).name}"):
        if modulator:
            require_modulator(cfg)
        return _run(cfg, name, trainer)


def _run(cfg: Mapping, name: str, trainer: dict) -> dict:
    from adadex.train.checkpoint import TRAINING_RUN, start_run
    from adadex.train.ppo import train

    check_keys(cfg, train_keys())
    if OmegaConf.is_config(cfg):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    tc, options = train_settings(cfg)
    blob = check_training_out(cfg)                  # before any work: nothing written when refused
    if blob is not None and blob["frames"] >= tc.ppo.total_frames:
        print(f"{name}: {tc.out} holds the finished run ({blob['frames']} of {tc.ppo.total_frames} frames): "
              f"nothing to do (a larger total_frames trains on)")
        return {}
    from adadex.data.build import dataset_at

    dataset_at(tc.dataset, preset=options.get("build_preset"), setting="dataset", seed=tc.seed,
               hint="set build_preset to build one")
    start_run(tc.out, TRAINING_RUN, fresh=blob is None)
    result = train(tc, run_name=name, **trainer)
    print(f"{name}: {result['frames']} frames, {result['iterations']} iterations -> {result['policy']}")
    print(json.dumps(result["eval"], indent=1))
    return result["eval"]


def require_modulator(cfg) -> None:
    """Refuse a modulator recipe's config without ``modulator.tracker`` (the frozen generalist): without it
    the settings describe a tracker run."""
    tracker = (cfg.get("modulator") or {}).get("tracker")
    if tracker is None:
        raise ConfigError("modulator.tracker is required: the frozen generalist's checkpoint "
                          "(modulator.tracker=runs/generalist/tracker.pt)")


def train_recipe(main: Callable, *, modulator: bool = False):
    """:func:`recipe_main` for a PPO recipe: :func:`train_keys`, :func:`check_training_out` (and, for a
    ``modulator`` recipe, :func:`require_modulator`)."""
    def guard(cfg):
        if modulator:
            require_modulator(cfg)
        return check_training_out(cfg)

    return recipe_main(main, schema=train_keys(), guard=guard)
