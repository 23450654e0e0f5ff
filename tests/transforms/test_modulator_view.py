"""The modulator's view: it shows the original reference the reward scores, the modulator's own
edit and last action, the phase and the previous frames — the same numbers on the transformed env
(training) and through make_policy's primer (evaluation)."""

import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from adadex.envs.observation import JOINT_POS, JOINT_TARGET, OBJECT_POSE
from adadex.envs.tracking import TrackingConfig, TrackingEnv
from adadex.modules.channels import ModulationConfig
from adadex.modules.modulator import Modulator
from adadex.modules.modulator_view import HISTORY, LAST_ACTION, STEPS, VIEW, ViewLayout
from adadex.modules.tracker import Tracker
from adadex.transforms.modulation import modulation


@pytest.fixture(scope="module")
def tracker():
    torch.manual_seed(0)
    return Tracker(hidden=(16, 16)).freeze()


def _env(dataset, tracker, channels, B=2, window=20, config=ModulationConfig(), history=2):
    view = ViewLayout(channels, history)
    env = TransformedEnv(TrackingEnv(dataset, num_worlds=B, split=None, seed=3, config=TrackingConfig(window=window)),
                         modulation(channels, tracker, config, view=view))
    return env, view


@pytest.mark.parametrize("channels", ["R+O+T", "T", "O"])
def test_specs_and_sizes(tiny_dataset, tracker, channels):
    env, view = _env(tiny_dataset, tracker, channels)
    check_env_specs(env)
    td = env.reset()
    assert td[VIEW].shape == (2, view.dim)
    assert ("edit" in dict(view.parts)) == ("R" in channels)
    env.close()


def test_view_shows_the_original_reference_and_its_own_state(tiny_dataset, tracker):
    """Large R edits: the tracker's observation moves, the view's original-reference errors are still
    the errors the env scores; last action, steps and history are the previous step's."""
    cfg = ModulationConfig(lambda_hand=0.2)
    env, view = _env(tiny_dataset, tracker, "R+T", config=cfg, window=16)
    part = view.slices()
    torch.manual_seed(0)
    td = env.reset()
    assert (td[LAST_ACTION] == 0).all() and (td[STEPS] == 0).all() and (td[HISTORY] == 0).all()
    resets = 0
    for t in range(18):                       # crosses the auto-reset at the window's end
        action = torch.rand(2, view.action_dim) * 2 - 1
        td["action"] = action
        prev_q, prev_target, prev_obj = td[JOINT_POS].clone(), td[JOINT_TARGET].clone(), td[OBJECT_POSE].clone()
        prev_steps = td[STEPS].clone()
        out = env.step(td)["next"]
        v = out[VIEW]
        # the joint error against the original reference: E_finger is what the env scores (no noise here)
        e_finger = v[:, part["original_error"]][:, 6:22].abs().mean(-1)
        torch.testing.assert_close(e_finger, out["privileged", "errors", "E_finger"], atol=1e-5, rtol=0)
        edit = v[:, part["edit"]]
        if t >= 1:
            assert edit.abs().max() > 0.05               # the accumulated edit is in view
        torch.testing.assert_close(v[:, part["last_action"]], action)
        torch.testing.assert_close(out[STEPS], prev_steps + 1)
        torch.testing.assert_close(v[:, part["phase"]], (prev_steps + 1) / 100.0)
        frame = out[HISTORY][:, 0]
        torch.testing.assert_close(frame, torch.cat([prev_q, prev_target, prev_obj], -1))
        torch.testing.assert_close(out[HISTORY][:, 1], td[HISTORY][:, 0])
        td = _next(env, td, out)
        done = out["done"].reshape(-1)
        if done.any():
            resets += 1
            assert (td[STEPS][done] == 0).all() and (td[LAST_ACTION][done] == 0).all()
            assert (td[STEPS][~done] > 0).all()
    assert resets
    env.close()


def _next(env, td, out):
    """What a rollout does between steps: the next observation, with done worlds reset."""
    from torchrl.envs.utils import step_mdp

    td = td.clone()
    td["next"] = out
    nxt = step_mdp(td, keep_other=True, exclude_action=False)
    if out["done"].any():
        nxt["_reset"] = out["done"].clone()
        nxt = env.reset(nxt)
        nxt = nxt.exclude("_reset")
    return nxt


def test_modulator_reads_the_view_and_trains_through_it(tiny_dataset, tracker):
    """The default modulator reads the view; the critic's value of the next step is defined (the env
    writes the view into ``next`` too), so GAE and PPO's loss run on a rollout."""
    from torchrl.objectives import ClipPPOLoss
    from torchrl.objectives.value import GAE

    torch.manual_seed(0)
    mod = Modulator("R+O+T", hidden=(16, 16))
    assert mod.obs_key == VIEW and mod.view.dim == ViewLayout("R+O+T", 3).dim
    env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3),
                         modulation("R+O+T", tracker, view=mod.view))
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        data = env.rollout(5, mod.sampling_policy(), break_when_any_done=False)
    assert data["next", VIEW].shape == (2, 5, mod.view.dim)
    GAE(gamma=0.99, lmbda=0.95, value_network=mod.critic)(data)
    losses = ClipPPOLoss(mod.actor, mod.critic)(data)
    assert all(torch.isfinite(v).all() for k, v in losses.items() if k.startswith("loss_"))
    env.close()


def test_channel_exploration_scales():
    """Each channel's head starts at its own scale: the registry's by default, or as given."""
    from adadex.modules.channels import CHANNELS

    torch.manual_seed(0)
    from tensordict import TensorDict

    mod = Modulator("R+O+T", hidden=(16,), inputs="observation")
    scale = mod(TensorDict({"observation": torch.zeros(4, 273)}, batch_size=[4]))["modulator", "scale"]
    sizes = mod.layout.channel_sizes
    for chunk, c in zip(scale.split(sizes, -1), mod.channels):
        torch.testing.assert_close(chunk, torch.full_like(chunk, CHANNELS[c].init_scale), atol=0.02, rtol=0.05)
    mod = Modulator("R+T", hidden=(16,), inputs="observation", init_scale={"T": 0.3})
    scale = mod(TensorDict({"observation": torch.zeros(4, 273)}, batch_size=[4]))["modulator", "scale"]
    torch.testing.assert_close(scale[:, 112:], torch.full((4, 22), 0.3), atol=0.02, rtol=0.05)
    with pytest.raises(ValueError, match="not among"):
        Modulator("R+T", hidden=(16,), init_scale={"O": 0.3})
