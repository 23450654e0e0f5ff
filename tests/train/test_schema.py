"""The recipes' one config schema (adadex.train.schema): keys are the dataclasses' fields, defaults come
from the dataclasses only, every field is settable from the command line, and the composed config is
the dataclass the code reads."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from adadex.errors import ConfigError
from adadex.train import config_store, schema
from adadex.train.config import ModulatorSettings, PolicyConfig, PPOConfig, TrainConfig
from adadex.train.recipe import train_settings

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
#: recipe file → the node its defaults list names first
ON_NODES = {"train_common": "adadex_train", "pipeline": "adadex_pipeline", "distill": "adadex_distill",
            "encoder": "adadex_encoder"}


def _compose(name: str, overrides=()):
    from hydra import compose, initialize_config_dir

    config_store.register()
    with initialize_config_dir(config_dir=str(RECIPES), version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides))


def _leaves(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict) and v:
            yield from _leaves(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def _get(d, dotted):
    for part in dotted.split("."):
        d = d[part]
    return d


@pytest.mark.parametrize("recipe, node", list(ON_NODES.items()))
def test_recipe_files_repeat_no_default(recipe, node):
    """A recipe file lists only what it changes: none of its values equals the node's default (a second
    copy of a default is how two defaults for one setting began)."""
    own = OmegaConf.to_container(OmegaConf.load(RECIPES / f"{recipe}.yaml"), resolve=False)
    own = {k: v for k, v in own.items() if k not in ("defaults", "hydra")}
    base = config_store.NODES[node]()
    for key, value in _leaves(own):
        default = _get(base, key)          # KeyError: a key that is not a field
        assert value != default, f"recipes/{recipe}.yaml repeats the default {key}={value!r}"


def test_every_train_field_is_settable_without_plus_and_reaches_trainconfig():
    """Each leaf of the adadex_train node can be set on the command line as ``key=value`` (no ``+``), and
    a changed value reaches the TrainConfig the recipe trains with."""
    node = config_store.train_node()
    leaves = dict(_leaves(node))
    assert {"ppo.total_frames", "collector.ray_address", "modulator.channels", "modulator.modulation.persistent",
            "env.window", "reward.w_prox", "randomization.object_xy_std", "policy.anchor", "sim.backend"} <= set(leaves)
    changed = ["ppo.total_frames=512", "collector.ray_address=auto", "env.window=60", "reward.w_prox=2.0",
               "randomization.object_xy_std=0.02", "policy.anchor=0.0", "split=[unseen_object,train]", "seed=3"]
    tc, options = train_settings(_compose("train_ppo", changed))
    assert (tc.ppo.total_frames, tc.collector.ray_address, tc.env, tc.reward, tc.randomization, tc.policy.anchor,
            tc.split, tc.seed) == (512, "auto", {"window": 60}, {"w_prox": 2.0}, {"object_xy_std": 0.02}, 0.0,
                                   ("unseen_object", "train"), 3)
    assert options == {"force": False, "build_preset": "small"}
    # every leaf, set to its own default, composes (no "+" needed for any field)
    overrides = [f"{k}={'null' if v is None else v}" for k, v in leaves.items()
                 if not isinstance(v, (list, dict)) and v != schema.MISSING and k not in ("dataset", "out")]
    _compose("train_ppo", overrides)


def test_train_recipe_defaults_are_the_dataclasses():
    """A PPO recipe with nothing set trains TrainConfig's, PPOConfig's and PolicyConfig's defaults."""
    tc, _ = train_settings(_compose("train_ppo"))
    assert tc.ppo == PPOConfig() and tc.policy == PolicyConfig() and tc.modulator is None
    assert (tc.env, tc.reward, tc.randomization) == ({}, {}, {})
    plain = TrainConfig(dataset=tc.dataset, out=tc.out)
    assert tc.to_dict() == plain.to_dict()


def test_modulator_node_is_modulator_settings(tmp_path):
    from adadex.modules.tracker import Tracker

    Tracker(hidden=(8,)).save(tmp_path / "t.pt")
    tc, _ = train_settings(_compose("train_modulator", [f"modulator.tracker={tmp_path / 't.pt'}",
                                                        "modulator.channels=R+T", "modulator.history=0",
                                                        "modulator.modulation.persistent=false"]))
    assert isinstance(tc.modulator, ModulatorSettings)
    assert (tc.modulator.channels, tc.modulator.history, tc.modulator.modulation) == ("R+T", 0, {"persistent": False})
    node = config_store.train_node()["modulator"]
    assert set(node) == {f.name for f in dataclasses.fields(ModulatorSettings)}


def test_changes_keeps_what_differs_and_refuses_what_is_not_a_field():
    assert schema.changes(PPOConfig, {"lr": 3e-4, "epochs": 2}, "ppo") == {"epochs": 2}
    assert schema.changes(PolicyConfig, {"hidden": [256, 256, 128]}, "policy") == {}      # a list is its tuple
    with pytest.raises(ConfigError, match="ppo: unknown setting 'lrr'"):
        schema.changes(PPOConfig, {"lrr": 1.0}, "ppo")


def test_evaluate_recipe_groups_are_the_dataclasses():
    cfg = _compose("evaluate", ["env.window=60", "randomization.object_xy_std=0.01"])
    c = OmegaConf.to_container(cfg)
    from adadex.modules.channels import ModulationConfig

    assert c["modulation"] == schema.defaults_of(ModulationConfig)
    assert c["env"]["window"] == 60 and c["randomization"]["object_xy_std"] == 0.01
