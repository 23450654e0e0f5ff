"""The channel registry: every record is bound to its transform, the config and the chain follow the
records, and a fourth channel is one more record (plus its transform class) — nothing else changes."""

import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from adadex.envs.tracking import TrackingEnv
from adadex.modules import channels
from adadex.modules.channels import CHANNELS, MOD, Channel, Field, ModulationConfig, ModulationLayout
from adadex.modules.modulator import Modulator
from adadex.modules.nets import GaussianHeads
from adadex.modules.tracker import Tracker
from adadex.transforms.modulation import ChannelTransform, TrackerInTheLoop, channel_transforms, modulation
from adadex.transforms.policy import make_policy


@pytest.fixture(scope="module")
def tracker():
    torch.manual_seed(0)
    return Tracker(hidden=(16, 16)).freeze()


def test_records_are_bound_and_drive_config_and_chain():
    assert list(CHANNELS) == ["R", "L", "C", "A", "O", "T", "K"]
    for name, record in CHANNELS.items():
        t = record.transform()
        assert isinstance(t, ChannelTransform) and t.channel is record
        assert t.out_keys_inv == list(record.keys)           # TorchRL way: what it reads on the inverse path
    fields = [f.name for c in CHANNELS.values() for f in c.fields]
    assert list(ModulationConfig.__dataclass_fields__) == fields
    assert [c.size for c in CHANNELS.values()] == [112, 2, 7, 1, 64, 22, 2]
    assert [t.channel.name for t in channel_transforms("T+O+R")] == ["R", "O", "T"]


def test_a_record_refuses_an_unknown_side_and_duplicates():
    with pytest.raises(ValueError, match="edits"):
        Channel("X", "x", entries=(((MOD, "x"), (3,)),), fields=(), edits="reward")
    with pytest.raises(ValueError, match="twice"):
        channels._registry(*CHANNELS.values(), Channel("X", "x", entries=(((MOD, "latent"), (3,)),), fields=(),
                                                         edits="action"))
    with pytest.raises(ValueError, match="no modulation channel 'X'"):
        type("Orphan", (ChannelTransform,), {}, channel="X")


def test_a_fourth_channel_is_one_record(tiny_dataset, tracker, monkeypatch):
    """A channel S that scales the tracker's action: its record and its transform class, nothing else."""
    scale = Channel("S", "tracker action scale", entries=(((MOD, "scale"), (22,)),),
                    fields=(Field("scale_bound", 0.2, "relative action scale per step"),), edits="action")
    monkeypatch.setattr(channels, "CHANNELS", channels._registry(*CHANNELS.values(), scale))
    monkeypatch.setattr(channels, "_TRANSFORMS", dict(channels._TRANSFORMS))
    config = channels._config_class(channels.CHANNELS)(scale_bound=0.1)

    class ScaleModulation(ChannelTransform, channel="S"):
        def __init__(self, config):
            super().__init__(config, ("action",))

        def _inv_call(self, td):
            a = self._inputs(td)
            if a is not None:
                td.set("action", td.get("action") * (1 + self.config.scale_bound * a[0]))
            return td

    assert channels.CHANNELS["S"].transform is ScaleModulation
    layout = ModulationLayout("S+O+T")
    assert layout.channels == ("O", "T", "S") and layout.dim == 64 + 22 + 22
    heads = next(m for m in Modulator("T+S", hidden=(8,)).modules() if isinstance(m, GaussianHeads))
    assert heads.head_sizes == (22, 22)
    chain = modulation("R+T+S", tracker, config)
    # Compose runs inverses last to first: flat split → R → tracker → T → S → env.
    assert [type(t).__name__ for t in chain] == ["ScaleModulation", "ActionModulation", "TrackerInTheLoop",
                                                  "ReferenceModulation", "FlatModulationAction"]
    assert isinstance(chain[2], TrackerInTheLoop)
    env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3),
                         modulation("O+S", tracker, config))
    check_env_specs(env)
    assert env.action_spec.shape == (2, 86)
    env.close()
    # The policy graph follows too, and equals the transformed env.
    torch.manual_seed(5)
    mod = Modulator("R+S", hidden=(8,), init_scale=1.0)
    policy = make_policy(tracker, mod, config=config)

    def run(env, pol):
        env.set_seed(7)
        torch.manual_seed(1)
        with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
            td = env.rollout(4, pol, break_when_any_done=False)
        env.close()
        return td

    a = run(TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3), policy.primer()), policy)
    b = run(TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3),
                           modulation("R+S", tracker, config, view=mod.view)), mod.actor)
    assert torch.equal(a["modulation", "sample"], b["action"])
    assert torch.equal(a["next", "proprio", "joint_pos"], b["next", "proprio", "joint_pos"])
