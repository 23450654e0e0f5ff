"""Tracker, Modulator, channel layout: shapes, bounds, modes, checkpoints, bad input."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.modules.channels import ModulationConfig, ModulationLayout, parse_channels
from adadex.modules.modulator import Modulator
from adadex.modules.nets import Normalizer, ObservationMoments, fit_normalizers
from adadex.modules.tracker import Tracker


def _obs(n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"observation": torch.randn(n, 273, generator=g)}, batch_size=[n])


@pytest.mark.parametrize("text, expected", [
    ("R+O+T", ("R", "O", "T")), ("T+R", ("R", "T")), ("none", ()), ("", ()), (" o ", ("O",)),
    (("T", "O"), ("O", "T")), ("R,T", ("R", "T"))])
def test_parse_channels(text, expected):
    assert parse_channels(text) == expected


@pytest.mark.parametrize("bad", ["R+X", "R+R", "ROT", "all"])
def test_bad_channels_are_named(bad):
    with pytest.raises(ValueError, match="channel"):
        parse_channels(bad)


def test_layout_sizes_and_split_round_trip():
    assert ModulationLayout("R+O+T").dim == 4 * 22 + 4 * 6 + 64 + 22
    assert ModulationLayout("none").dim == 0
    layout = ModulationLayout("R+O+T")
    flat = torch.arange(2 * layout.dim, dtype=torch.float32).reshape(2, layout.dim)
    parts = layout.split(flat)
    assert parts[("modulation", "ref_hand")].shape == (2, 4, 22)
    assert parts[("modulation", "ref_object")].shape == (2, 4, 6)
    assert parts[("modulation", "latent")].shape == (2, 64)
    assert parts[("modulation", "action")].shape == (2, 22)
    assert torch.equal(torch.cat([v.reshape(2, -1) for v in parts.values()], -1), flat)
    with pytest.raises(ValueError, match="198 entries"):
        layout.split(torch.zeros(2, 100))


def test_modulation_config_rejects_bad_values():
    with pytest.raises(ValueError, match="lambda_hand"):
        ModulationConfig(lambda_hand=-0.1)
    with pytest.raises(ValueError, match="action_bound"):
        ModulationConfig(action_bound=float("nan"))


def test_tracker_actor_bounds_modes_and_critic():
    torch.manual_seed(0)
    tracker = Tracker(hidden=(32, 32), max_action=0.1)
    td = tracker(_obs())
    assert td["action"].shape == (6, 22) and (td["action"].abs() <= 0.1).all()
    assert td["action_log_prob"].shape == (6,) and torch.isfinite(td["action_log_prob"]).all()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a1 = tracker(_obs())["action"]
        a2 = tracker(_obs())["action"]
        loc = tracker(_obs())["tracker", "loc"]
    assert torch.equal(a1, a2)
    torch.testing.assert_close(a1, 0.1 * torch.tanh(loc))
    with set_exploration_type(ExplorationType.RANDOM):   # as TorchRL's collectors run it
        b1, b2 = tracker(_obs())["action"], tracker(_obs())["action"]
    assert not torch.equal(b1, b2)
    assert tracker.critic(_obs())["state_value"].shape == (6, 1)


def test_deterministic_action_is_differentiable_for_behaviour_cloning():
    torch.manual_seed(0)
    tracker = Tracker(hidden=(32, 32))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        loss = (tracker(_obs())["action"] - 0.05).pow(2).mean()
    loss.backward()
    grads = [p.grad for p in tracker.actor.parameters() if p.requires_grad]
    assert grads and all(g is not None for g in grads) and any(g.abs().sum() > 0 for g in grads)


def test_freeze_stops_gradients():
    tracker = Tracker(hidden=(16,)).freeze()
    assert not any(p.requires_grad for p in tracker.parameters()) and not tracker.training


def test_tracker_checkpoint_round_trip(tmp_path):
    torch.manual_seed(1)
    tracker = Tracker(hidden=(32, 16), max_action=0.08)
    fit_normalizers(tracker, torch.randn(100, 273) * 3 + 1)
    path = tracker.save(tmp_path / "t.pt")
    again = Tracker.load(path)
    assert again.config == tracker.config
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(tracker(_obs())["action"], again(_obs())["action"])
    assert torch.equal(tracker.critic(_obs())["state_value"], again.critic(_obs())["state_value"])


def _residual_inputs(n=8, seed=1):
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"observation": 0.3 * torch.randn(n, 273, generator=g),
                       ("proprio", "joint_target"): 0.3 * torch.randn(n, 22, generator=g)}, batch_size=[n])


def _deterministic_correction(tracker, td):
    """The deterministic action minus kinematic replay's (the residual tracker's feed-forward)."""
    from adadex.envs.observation import NEXT_REF_JOINTS

    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        action = tracker.actor(td.clone())["action"]
    return action - (td["observation"][:, NEXT_REF_JOINTS] - td["proprio", "joint_target"])


@pytest.mark.parametrize("loc_bound", [0.0, 5.0])
def test_a_residual_tracker_with_a_zero_mean_is_replay_whatever_its_bound(loc_bound):
    """With the network's mean at 0 the action is the feed-forward, bounded mean or not. (TorchRL's own
    ``tanh_loc`` adds the bounds' centre — here the feed-forward — to the pre-tanh mean, which made
    this correction ``residual·tanh(feed-forward)``: up to 0.2 rad on these inputs.)"""
    tracker = Tracker(hidden=(16,), residual=0.25, init_scale=0.05, loc_bound=loc_bound).zero_mean()
    assert _deterministic_correction(tracker, _residual_inputs()).abs().max() < 1e-6


def test_checkpoints_from_before_the_in_network_bound_act_as_trained(tmp_path):
    """A residual tracker saved with ``loc_bound`` but without ``torchrl_tanh_loc`` was trained with
    TorchRL's ``tanh_loc``: it loads with it and gives the same actions as then (the shifted mean);
    new checkpoints keep the in-network bound."""
    torch.manual_seed(3)
    td = _residual_inputs()
    legacy = Tracker(hidden=(16,), residual=0.25, init_scale=0.05, loc_bound=5.0, torchrl_tanh_loc=True)
    blob = {"kind": "tracker", "config": {k: v for k, v in legacy.config.items() if k != "torchrl_tanh_loc"},
            "state_dict": legacy.state_dict()}
    torch.save(blob, tmp_path / "old.pt")
    again = Tracker.load(tmp_path / "old.pt")
    assert again.config["torchrl_tanh_loc"] is True
    shifted = _deterministic_correction(again, td)
    torch.testing.assert_close(shifted, _deterministic_correction(legacy, td), rtol=0, atol=0)
    assert shifted.abs().max() > 0.05                           # the old parametrization's offset, not replay
    fresh = Tracker.load(Tracker(hidden=(16,), residual=0.25, loc_bound=5.0).save(tmp_path / "new.pt"))
    assert fresh.config["torchrl_tanh_loc"] is False


def test_checkpoints_from_before_loc_bound_load_unbounded(tmp_path):
    """A tracker saved before ``loc_bound`` existed has no such key: it loads with an unbounded mean,
    as it was trained, and acts as before; a bounded one keeps its bound."""
    torch.manual_seed(2)
    old = Tracker(hidden=(32, 16))
    blob = {"kind": "tracker", "config": {k: v for k, v in old.config.items() if k != "loc_bound"},
            "state_dict": old.state_dict()}
    torch.save(blob, tmp_path / "old.pt")
    again = Tracker.load(tmp_path / "old.pt")
    assert again.config["loc_bound"] == 0.0
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(old(_obs())["action"], again(_obs())["action"])
    bounded = Tracker.load(Tracker(hidden=(32, 16), loc_bound=5.0).save(tmp_path / "new.pt"))
    assert bounded.config["loc_bound"] == 5.0
    with pytest.raises(ValueError, match="loc_bound"):
        Tracker(loc_bound=-1.0)


def test_bad_checkpoints_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        Tracker.load(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pt"):
        Tracker.load(tmp_path / "junk.pt")
    Modulator("T", hidden=(8,)).save(tmp_path / "m.pt")
    with pytest.raises(ValueError, match="not a tracker checkpoint"):
        Tracker.load(tmp_path / "m.pt")


def test_normalizer_fit_and_clip():
    x = torch.randn(500, 4) * torch.tensor([1.0, 10.0, 0.0, 2.0]) + torch.tensor([0.0, 5.0, 3.0, -1.0])
    n = Normalizer(4).fit(x)
    y = n(x)
    assert y[:, [0, 1, 3]].std(0).sub(1).abs().max() < 0.05 and y.mean(0).abs().max() < 0.05
    assert torch.equal(n.scale[2], torch.tensor(1.0))            # constant entry: shifted, not blown up
    assert n(torch.full((1, 4), 1e6)).max() == n.clip
    with pytest.raises(ValueError, match="finite"):
        n.fit(torch.full((3, 4), float("nan")))


def test_observation_moments_merge_batches_into_the_whole_sample():
    torch.manual_seed(0)
    batches = [torch.randn(n, 3) * s + m for n, s, m in ((50, 1.0, 0.0), (7, 4.0, 10.0), (300, 0.1, -2.0))]
    m = ObservationMoments()
    for b in batches:
        m.update(b)
    whole = torch.cat(batches)
    assert m.count == len(whole)
    torch.testing.assert_close(m.mean, whole.double().mean(0))
    torch.testing.assert_close(m.std, whole.double().std(0))
    tracker = Tracker(hidden=(16,), residual=0.25)
    obs = torch.cat([torch.randn(40, 273), torch.full((40, 273), 3.0)])        # the last half constant at 3
    obs[:, 200:] = 3.0
    m = ObservationMoments()
    m.update(obs[:40]), m.update(obs[40:])
    m.apply(tracker)
    norms = [mod for mod in tracker.modules() if isinstance(mod, Normalizer)]
    assert len(norms) == 2                                          # actor and critic
    fitted = Normalizer(273).fit(obs)                               # the same as fitting on everything
    for n in norms:
        torch.testing.assert_close(n.loc, fitted.loc)
        torch.testing.assert_close(n.scale, fitted.scale)
        assert torch.equal(n.scale[200:], torch.ones(73))           # constant entries keep scale 1
    with pytest.raises(ValueError, match="non-finite"):
        m.update(torch.full((2, 273), float("nan")))
    with pytest.raises(ValueError, match="≥ 2 samples"):
        ObservationMoments().apply(tracker)


@pytest.mark.parametrize("channels, dim", [("R+O+T", 198), ("R", 112), ("O", 64), ("T", 22), ("R+T", 134),
                                           ("O+T", 86), ("R+O", 176)])
def test_modulator_is_sized_by_its_channels(channels, dim):
    torch.manual_seed(0)
    mod = Modulator(channels, hidden=(32, 32), inputs="observation")
    assert mod.layout.dim == dim
    td = mod(_obs())
    assert td["action"].shape == (6, dim) and (td["action"].abs() <= 1).all()
    assert mod.critic(_obs())["state_value"].shape == (6, 1)


def test_untrained_modulator_starts_near_identity():
    torch.manual_seed(0)
    mod = Modulator("R+O+T", hidden=(64, 64), inputs="observation")
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a = mod(_obs(32))["action"]
    assert a.abs().max() < 0.1, a.abs().max()


def test_modulator_needs_a_channel_and_round_trips(tmp_path):
    with pytest.raises(ValueError, match="at least one channel"):
        Modulator("none")
    torch.manual_seed(0)
    mod = Modulator("R+T", hidden=(16, 16), inputs="observation", init_scale={"T": 0.2})
    again = Modulator.load(mod.save(tmp_path / "m.pt"))
    assert again.channels == ("R", "T") and again.config == mod.config
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(mod(_obs())["action"], again(_obs())["action"])


def test_a_context_free_channel_learns_one_choice_for_every_view(tmp_path):
    """Channel K's gains context-free: the same distribution whatever the view, moved by training
    (its head's bias), while the other channel still reads the view; saved and loaded as it was."""
    torch.manual_seed(0)
    mod = Modulator("T+K", hidden=(16, 16), inputs="observation", context_free=["K"])
    k = mod.layout.split(torch.arange(mod.layout.dim))
    gain = next(v for key, v in k.items() if key[-1] == "gain")
    head = mod.actor._sampling_parts[0].heads[mod.layout.channels.index("K")]
    with torch.no_grad():
        for h in mod.actor._sampling_parts[0].heads:
            h.weight.normal_()
            h.bias.normal_()
    out = mod.actor(_obs(8))
    loc, scale = out["modulator", "loc"], out["modulator", "scale"]
    assert torch.equal(loc[:, gain], loc[:1, gain].expand(8, -1))
    assert torch.equal(scale[:, gain], scale[:1, gain].expand(8, -1))
    assert not torch.equal(loc[:, :22], loc[:1, :22].expand(8, -1))     # T reads the view
    loc[:, gain].sum().backward()
    assert head.weight.grad is None and head.bias.grad.abs().sum() > 0
    assert torch.allclose(loc[0, gain], 30.0 * head.bias[:2])       # the bias × context_free_rate
    assert torch.allclose(torch.tensor(mod.context_free_actions()["gain"]), torch.tanh(loc[0, gain]).detach())
    with set_exploration_type(ExplorationType.DETERMINISTIC):       # what a deterministic run takes
        assert torch.allclose(mod(_obs(3))["action"][:, gain], torch.tanh(loc[:3, gain]).detach(), atol=1e-6)
    again = Modulator.load(mod.save(tmp_path / "m.pt"))
    assert again.config["context_free"] == ["K"]
    assert torch.equal(again.actor(_obs(8))["modulator", "loc"], loc.detach())
    with pytest.raises(ValueError, match="context_free.*'R'"):
        Modulator("T+K", hidden=(16, 16), inputs="observation", context_free=["R"])


def test_a_focused_channel_reads_only_its_view_parts(tmp_path):
    """Channel A's head focused on the object's start offset: its distribution moves with those three
    view entries and with nothing else, while T still reads the whole view; the focus is saved and
    loaded with the checkpoint; a focus the modulator cannot read is refused naming it."""
    torch.manual_seed(0)
    mod = Modulator("A+T", hidden=(16, 16), focus={"A": ["start_offset"]})
    net = mod.actor._sampling_parts[0]
    with torch.no_grad():
        for h in net.heads:
            h.weight.normal_()
    a = mod.layout.channels.index("A")
    view = torch.randn(4, mod.view.dim, requires_grad=True)
    loc, scale = net(view)
    offset = mod.view.slices()["start_offset"]
    grad_a, = torch.autograd.grad(loc[:, a].sum() + scale[:, a].sum(), view, retain_graph=True)
    read = grad_a.abs().sum(0) > 0
    assert read[offset].all() and read.sum() == offset.stop - offset.start
    grad_t, = torch.autograd.grad(loc[:, a + 1:].sum(), view)
    assert (grad_t.abs().sum(0) > 0).sum() > 100            # T: the whole view
    again = Modulator.load(mod.save(tmp_path / "m.pt"))
    assert again.config["focus"] == {"A": ["start_offset"]}
    assert torch.equal(again.actor._sampling_parts[0](view)[0], loc)
    for focus, match in (({"K": ["start_offset"]}, "'K' is not a channel"), ({"A": ["nope"]}, r"\['nope'\]"),
                         ({"A": []}, "no parts")):
        with pytest.raises(ValueError, match=match):
            Modulator("A+T", hidden=(8,), focus=focus)
    with pytest.raises(ValueError, match="inputs='view'"):
        Modulator("A+T", hidden=(8,), inputs="observation", focus={"A": "start_offset"})
