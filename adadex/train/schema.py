"""The config schema the recipes share, made from the config dataclasses: one set of keys, one default
per setting.

A recipe's keys are a config dataclass's fields; its node (:mod:`adadex.train.config_store`, stored in
Hydra's ConfigStore) is built from the dataclasses' own defaults (:func:`defaults_of`), and the composed
config goes back through them (``TrainConfig.from_dict``), so their checks — one line naming the
setting — validate it. :func:`keys_of` is a node's strict-key schema (:func:`adadex.train.recipe.recipe_main`
refuses any other key). OmegaConf's typed structured configs are not used as the node itself: they cannot
express fields such as ``ModulatorSettings.init_scale`` (a number, a per-channel mapping or null).

Settings that are mappings of changes (``env``, ``reward``, ``randomization``, ``modulation``) appear in
a node with every field of their class (:func:`change_nodes`, :func:`modulation_node`), so any of them
is set as ``reward.w_prox=1.0``; a config keeps only the entries that differ from the class default
(:func:`changes`), so a run's stored settings name what it changed.

This module imports no other part of :mod:`adadex.train` (the configs use it).

>>> from adadex.train.config import PPOConfig
>>> defaults_of(PPOConfig)["total_frames"], keys_of({"ppo": {"lr": 0.1}, "seed": 0})
(1000000, {'ppo': {'lr': None}, 'seed': None})
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from adadex.errors import ConfigError

#: a required field in a node: OmegaConf's "missing value" (the recipe or the command line must set it)
MISSING = "???"


def _plain(v):
    """A default as YAML would write it: tuples as lists, dataclasses as mappings."""
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: _plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if isinstance(v, Mapping):
        return {k: _plain(x) for k, x in v.items()}
    return v


def field_default(cls, name: str):
    """Dataclass ``cls``'s default of field ``name`` (a ``default_factory`` called), or :data:`MISSING`
    for a required field."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else MISSING


def check_fields(cls, values: Mapping, where: str, *, drop=()) -> None:
    """Refuse, in one :class:`ConfigError` naming ``where`` and the known fields, the keys of ``values``
    that are not fields of dataclass ``cls`` (or are in ``drop``)."""
    known = sorted(f.name for f in dataclasses.fields(cls) if f.name not in drop)
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ConfigError(f"{where}: unknown setting{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
                          f"(known: {', '.join(known)})")


def defaults_of(cls, *, drop=(), expand: Mapping | None = None, **values) -> dict:
    """The node of dataclass ``cls``: ``{field: default}``, a nested dataclass's default as its own
    mapping, a required field as :data:`MISSING`; fields in ``drop`` left out; ``expand`` maps a field
    to the node that stands for it (a mapping-of-changes field shown with its class's fields);
    ``values`` replace defaults."""
    node = {}
    for f in dataclasses.fields(cls):
        if f.name in drop:
            continue
        node[f.name] = _plain(field_default(cls, f.name))
    node.update(expand or {})
    unknown = set(values) - set(node)
    if unknown:
        raise ConfigError(f"{cls.__name__}: no field {sorted(unknown)}")
    node.update({k: _plain(v) for k, v in values.items()})
    return node


def keys_of(node: Mapping) -> dict:
    """The strict-key schema of a node: ``{key: None}`` for a value, a nested schema for a non-empty
    mapping (an empty one, or ``None``, takes any mapping: its class checks it where it is used)."""
    return {k: keys_of(v) if isinstance(v, Mapping) and v else None for k, v in node.items()}


def changes(cls, values: Mapping | None, where: str, *, drop=()) -> dict:
    """The entries of ``values`` that differ from dataclass ``cls``'s defaults (lists and tuples alike);
    a key that is not a field of ``cls`` (or is in ``drop``) is refused naming ``where``."""
    values = dict(values or {})
    check_fields(cls, values, where, drop=drop)
    base = defaults_of(cls, drop=drop)
    return {k: v for k, v in values.items() if _plain(v) != base[k]}


# ----------------------------------------------------------------------------------------------
# The groups every node shares

def modulation_node() -> dict:
    """:class:`~adadex.modules.channels.ModulationConfig`'s fields and defaults."""
    from adadex.modules.channels import ModulationConfig

    return defaults_of(ModulationConfig)


def change_nodes() -> dict:
    """``env`` (:class:`~adadex.envs.tracking.TrackingConfig` but its reward), ``reward``
    (:class:`~adadex.envs.reward.RewardConfig`) and ``randomization`` (Table 3's
    :class:`~adadex.envs.randomization.Randomization`, but the per-joint effects and patches set in code)."""
    from adadex.envs.randomization import Randomization
    from adadex.envs.reward import RewardConfig
    from adadex.envs.tracking import TrackingConfig

    return {"env": defaults_of(TrackingConfig, drop=ENV_CODE_ONLY),
            "reward": defaults_of(RewardConfig),
            "randomization": defaults_of(Randomization, drop=RANDOMIZATION_CODE_ONLY)}


#: TrackingConfig fields not set through ``env`` (the reward has its own node)
ENV_CODE_ONLY = ("reward",)
#: Randomization fields set in code only (per-joint effect ranges, a patch to randomize around)
RANDOMIZATION_CODE_ONLY = ("effects", "patch")


def env_settings(env: Mapping | None, reward: Mapping | None, where: str):
    """The :class:`~adadex.envs.tracking.TrackingConfig` with ``env`` and ``reward`` changes (an evaluation
    recipe's ``env`` and ``reward`` nodes); a bad key or value is one :class:`ConfigError` naming
    ``where``."""
    from adadex.envs.reward import RewardConfig
    from adadex.envs.tracking import TrackingConfig

    env = changes(TrackingConfig, env, f"{where}.env", drop=ENV_CODE_ONLY)
    reward = changes(RewardConfig, reward, f"{where}.reward")
    try:
        return TrackingConfig(**env, reward=RewardConfig(**reward))
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: {e}") from None
