"""The MuJoCo Warp backend (``BatchedSim(..., backend="warp")``) against the mujoco.rollout backend, on
Warp's CPU device. Every sim here uses one scene structure (the uniform-layout scenes) and the same
capacities, so Warp compiles its kernels once per session (about a minute cold, cached afterwards)."""

import copy
import os
import sys

import mujoco
import numpy as np
import pytest

from adadex.errors import ConfigError
from adadex.sim.batched import BatchedSim
from adadex.sim.robot import joint_limits
from adadex.sim.scene import OBJECT_QPOS, build_scene_model, build_scene_spec, home_state
from tests.sim.test_batched import diverging_model

#: Warp's device for these tests: its CPU device here and in CI; ``cuda:0`` checks the same on a GPU.
DEVICE = os.environ.get("ADADEX_WARP_TEST_DEVICE", "cpu")


def test_missing_extra_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco_warp", None)      # import fails as if not installed
    with pytest.raises(ConfigError, match=r'pip install "adadex\[warp\]"'):
        BatchedSim(build_scene_model("mug_00", uniform_layout=True), 2, backend="warp")
    with pytest.raises(ConfigError, match="backend must be one of"):
        BatchedSim(build_scene_model("mug_00", uniform_layout=True), 2, backend="jax")


@pytest.fixture(scope="module")
def warp():
    """Warp on its CPU device (or ``ADADEX_WARP_TEST_DEVICE``), quiet; the kernel cache is Warp's own
    (kept between runs)."""
    pytest.importorskip("mujoco_warp")
    import warp as wp

    wp.config.quiet = True
    wp.init()
    wp.set_device(DEVICE)            # where TrackingEnv(backend="warp") puts its worlds
    return wp


@pytest.fixture(scope="module")
def mug():
    return build_scene_model("mug_00", uniform_layout=True)


def _sims(models, **kw):
    return (BatchedSim(models, backend="warp", device=DEVICE, **kw), BatchedSim(models, nthread=2))


def _random_ctrls(model, steps, batch, seed, sigma=0.05):
    lim = joint_limits()
    rng = np.random.default_rng(seed)
    _, home = home_state(model)
    return np.clip(home + np.cumsum(rng.normal(0, sigma, (steps, batch, 22)), axis=0), lim[:, 0], lim[:, 1])


def _overflow(sim):
    """Capacity overflow flags set so far (solver iteration limits are not overflows)."""
    return int(np.bitwise_or.reduce(sim._overflow.cpu().numpy())) & sim._capacity_bits


def _scaled_gains(model, k):
    m = copy.copy(model)
    m.actuator_gainprm[:, 0] *= k
    m.actuator_biasprm[:, 1] *= k
    return m


def test_free_motion_and_per_world_gains_match_rollout(warp, mug):
    """Worlds with servo gains ×1, ×0.5, ×2 (per-world parameters) follow their own rollout models
    to 1e-5 rad after 1 s of changing commands; the device readout holds the same numbers."""
    models = [mug, _scaled_gains(mug, 0.5), _scaled_gains(mug, 2.0)]
    ws, rs = _sims(models)
    assert "actuator_gainprm" in ws._batched
    qpos, _ = home_state(mug)
    ws.reset(qpos=qpos)
    rs.reset(qpos=qpos)
    for c in _random_ctrls(mug, 12, 3, seed=1):
        a, b = ws.step(c), rs.step(c)
    assert not a.unstable.any() and _overflow(ws) == 0
    np.testing.assert_allclose(a.time, b.time, atol=1e-5)
    assert np.abs(a.joint_pos - b.joint_pos).max() < 1e-5
    assert np.abs(a.link_pose - b.link_pose).max() < 1e-5
    assert np.abs(a.joint_vel - b.joint_vel).max() < 1e-3
    # the gains matter: the three worlds moved apart under the same commands
    assert np.abs(a.joint_pos[1] - a.joint_pos[2]).max() > 1e-3
    dev = ws.device_readout()
    assert dev.joint_pos.device.type == DEVICE.split(":")[0] and dev.link_pose.shape == (3, 5, 7)
    np.testing.assert_allclose(dev.joint_pos.cpu().numpy(), a.joint_pos, atol=1e-7)
    np.testing.assert_allclose(ws.state[:, 1:1 + mug.nq], rs.state[:, 1:1 + mug.nq], atol=1e-4)
    # set_models writes a world's new parameters: world 1 back to nominal gains matches world 0
    ws.set_models([1], [mug])
    ws.reset(qpos=qpos)
    for c in _random_ctrls(mug, 3, 1, seed=2):
        a = ws.step(np.repeat(c, 3, axis=0))
    # equal on Warp's CPU device; on a GPU two worlds' float32 sums may round apart (3e-8 rad on an H100)
    np.testing.assert_allclose(a.joint_pos[0], a.joint_pos[1], rtol=0, atol=1e-6)
    # step takes a torch tensor too; the full-physics state (mj_getState's layout) round-trips
    import torch

    saved, c = ws.state, np.repeat(c, 3, axis=0)
    assert saved.shape == (3, mujoco.mj_stateSize(mug, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    first = ws.step(torch.from_numpy(c).float())
    ws.set_state(saved)
    again = ws.step(c)
    np.testing.assert_allclose(again.joint_pos, first.joint_pos, atol=1e-6)
    ws.close()


def test_contact_drop_and_push_match_rollout(warp, mug):
    """The mug dropped from 2 cm while the arm moves: object within 0.1 mm, joints within 1e-3 rad."""
    ws, rs = _sims([mug, mug])
    qpos, _ = home_state(mug)
    qpos[OBJECT_QPOS.start + 2] += 0.02
    ws.reset(qpos=qpos)
    rs.reset(qpos=qpos)
    for c in _random_ctrls(mug, 18, 2, seed=3):
        a, b = ws.step(c), rs.step(c)
    assert not a.unstable.any() and _overflow(ws) == 0
    assert np.abs(a.object_pose - b.object_pose).max() < 1e-4
    assert np.abs(a.joint_pos - b.joint_pos).max() < 1e-3
    assert a.object_pose[0, 2] < qpos[OBJECT_QPOS.start + 2] - 0.015      # it did fall onto the table
    ws.close()


def test_scripted_grasp_lifts_and_slips_as_rollout(warp, mug, monkeypatch):
    """The scripted pinch-and-lift of the mug: lift and slip agree with the rollout backend."""
    import adadex.sim.grasp as grasp

    ref = grasp.scripted_grasp_lift("mug_00", model=mug, hold_s=1.0)
    made = []

    def warp_sim(model, batch, nthread=0):
        made.append(BatchedSim(model, batch, backend="warp", device=DEVICE))
        return made[-1]

    monkeypatch.setattr(grasp, "BatchedSim", warp_sim)
    got = grasp.scripted_grasp_lift("mug_00", model=mug, hold_s=1.0)
    assert not got.unstable and not ref.unstable
    assert ref.lift_achieved > 0.05
    # measured: lift 81.215 vs 81.231 mm, slip 5.721 vs 5.725 mm, heights within 0.06 mm
    assert abs(got.lift_achieved - ref.lift_achieved) < 2e-4, (got.lift_achieved, ref.lift_achieved)
    assert abs(got.max_slip - ref.max_slip) < 2e-4, (got.max_slip, ref.max_slip)
    assert np.abs(got.object_height - ref.object_height).max() < 2e-4
    assert made[0].overflow_count == 0          # no world ran out of constraint rows (contacts would raise)


def test_unstable_world_is_flagged_and_others_unaffected(warp):
    spec = build_scene_spec("mug_00", uniform_layout=True)
    stable = spec.compile()
    wild = diverging_model(spec)
    ws, rs = _sims([stable, wild, stable])
    qpos, ctrl = home_state(stable)
    ws.reset(qpos=qpos)
    rs.reset(qpos=qpos)
    target = ctrl.copy()
    target[:6] += 0.5
    flagged = np.zeros(3, bool)
    for _ in range(6):
        a = ws.step(np.tile(target, (3, 1)))
        b = rs.step(np.tile(target, (3, 1)))
        flagged |= a.unstable
    assert flagged.tolist() == [False, True, False]
    assert np.abs(a.joint_pos[[0, 2]] - b.joint_pos[[0, 2]]).max() < 1e-5
    ws.reset(qpos=qpos, worlds=[1])            # the caller puts the world back
    assert not ws.readout().unstable.any()
    ws.close()


def test_capacity_overflows_never_pass_silently(warp, mug):
    """Too few contact slots (shared by all worlds) raise naming nconmax; too few constraint rows
    (per world) flag that world unstable until it is reset."""
    qpos, ctrl = home_state(mug)
    ws = BatchedSim([mug], backend="warp", device=DEVICE, nconmax=2)
    ws.reset(qpos=qpos)
    with pytest.raises(ConfigError, match="raise nconmax"):
        ws.step(ctrl[None])
    ws = BatchedSim([mug, mug], backend="warp", device=DEVICE, njmax=8)
    ws.reset(qpos=qpos)
    assert ws.step(np.tile(ctrl, (2, 1))).unstable.tolist() == [True, True]
    assert ws.overflow_count == 2
    ws.reset(qpos=qpos, worlds=[0])
    assert _overflow(ws) != 0 and int(ws._overflow[0]) == 0


def test_unbatchable_difference_is_refused(warp, mug):
    other = copy.copy(mug)
    other.geom_condim[-1] = 1 if mug.geom_condim[-1] != 1 else 3
    with pytest.raises(ConfigError, match="geom_condim"):
        BatchedSim([mug, other], backend="warp", device=DEVICE)
    with pytest.raises(ConfigError, match="uniform_layout"):
        BatchedSim([mug, build_scene_model("torus_00")], backend="warp", device=DEVICE)
    sim = BatchedSim([mug, mug], backend="warp", device=DEVICE)
    with pytest.raises(ConfigError, match="geom_condim"):
        sim.set_models([1], [other])
    assert sim.models[1] is mug


def test_worlds_with_different_objects_and_sizes_match_rollout(warp, mug):
    """Uniform-layout scenes of different objects (1, 16, 21 parts) and a resized mug, dropped from
    2 cm: each world rests on its own object's bottom, as in its rollout model (mesh pool, parked
    pads); a world swapped to another object by set_models follows that object."""
    from adadex.sim import objects

    names = ["cube_050", "torus_00", "sphere_03"]
    models = [mug] + [build_scene_model(n, uniform_layout=True) for n in names]
    models.append(build_scene_model("mug_00", uniform_layout=True, object_scale=1.2))
    ws, rs = _sims(models)
    qpos = np.stack([home_state(m)[0] for m in models])
    qpos[:, OBJECT_QPOS.start + 2] += 0.02
    for w, q in enumerate(qpos):
        ws.reset(qpos=q, worlds=[w])
        rs.reset(qpos=q, worlds=[w])
    ctrl = np.stack([home_state(m)[1] for m in models])
    for _ in range(18):
        a, b = ws.step(ctrl), rs.step(ctrl)
    assert not a.unstable.any() and _overflow(ws) == 0
    # measured: heights within 0.01 mm; across the table within 1 µm, but for the torus, which
    # lands on its 16 parts and slides 0.48 mm further than in C MuJoCo (as much alone in a sim
    # of its own: MuJoCo Warp's multi-contact, not the pool)
    assert np.abs(a.object_pose[:, 2] - b.object_pose[:, 2]).max() < 1e-4
    assert np.abs(a.object_pose[:, :2] - b.object_pose[:, :2]).max() < 1e-3
    assert np.abs(np.delete(a.object_pose, 2, axis=0)[:, :2] - np.delete(b.object_pose, 2, axis=0)[:, :2]).max() < 1e-5
    assert np.abs(a.object_pose[:, 3:] - b.object_pose[:, 3:]).max() < 2e-3
    expected = [objects.get_object(n).half_height for n in ["mug_00"] + names]
    assert np.abs(a.object_pose[:4, 2] - expected).max() < 3e-3
    ws.set_models([0], [models[1]])
    rs.set_models([0], [models[1]])
    for sim in (ws, rs):
        sim.reset(qpos=qpos[1], worlds=[0])
    for _ in range(12):
        a, b = ws.step(ctrl), rs.step(ctrl)
    assert abs(a.object_pose[0, 2] - objects.get_object("cube_050").half_height) < 3e-3
    assert np.abs(a.object_pose[0, :3] - b.object_pose[0, :3]).max() < 1e-4
    ws.close()


@pytest.mark.parametrize("randomize", [False, True], ids=["patch", "patch+randomization"])
def test_tracking_env_observes_the_same_on_both_backends(warp, tiny_dataset, randomize):
    """TrackingEnv(backend="warp") hands out the observations, rewards and errors of backend="rollout"
    for a few steps: with a model patch of every effect stage on every world, and under Table 3's randomization (per-world
    masses, frictions, gains, object sizes and restitution, all drawn around the patch; the tiny
    dataset's references put two objects, at three sizes, in the three worlds). Measured: observations
    within 1.3e-5, rewards within 5e-5 of their size."""
    import torch

    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import TrackingEnv
    from adadex.sim.patch import ModelPatch

    # one effect of every stage: model (gains, damping, friction, a payload), structure (a transport
    # delay: actuator history; a first-order lag: an activation), command (backlash), sensor (encoder)
    patch = (ModelPatch().with_effect("kp_scale", ["arm_j1", "if_pip"], [0.8, 0.9]).with_effect("damping", ["if_pip"], 0.1)
             .with_effect("coulomb_friction", ["arm_j4"], 0.5).with_effect("payload_mass", ["arm_j6"], 0.2)
             .with_effect("actuator_delay", ["arm_j2", "if_pip"], [0.03, 0.05])
             .with_effect("actuator_lag", ["arm_j3", "mf_pip"], [0.04, 0.1])
             .with_effect("backlash", ["arm_j5"], 0.01).with_effect("encoder_offset", ["if_dip"], 0.02))
    kw = dict(num_worlds=3, split=None, seed=5, patch=patch, nthread=0,
              randomize=Randomization(proprio_noise=0.0, action_noise_uncorrelated=0.0) if randomize else None)
    envs = {b: TrackingEnv(tiny_dataset, backend=b, **kw) for b in ("rollout", "warp")}
    tds = {b: env.reset() for b, env in envs.items()}
    assert envs["warp"].current_references == envs["rollout"].current_references
    rng = np.random.default_rng(0)
    for _ in range(4):
        action = torch.as_tensor(rng.uniform(-0.05, 0.05, (3, 22)), dtype=torch.float32)
        tds = {b: env.step(tds[b].set("action", action.clone())) for b, env in envs.items()}
        a, b = tds["warp"]["next"].cpu(), tds["rollout"]["next"]        # the warp env's tensors: its device's
        torch.testing.assert_close(a["observation"], b["observation"], atol=1e-4, rtol=0)
        torch.testing.assert_close(a["reward"], b["reward"], atol=1e-4, rtol=1e-4)
        assert torch.equal(a["done"], b["done"])
        tds = {k: v["next"].clone() for k, v in tds.items()}
    assert envs["warp"].sim.overflow_count == 0 and envs["warp"].unstable_count == 0
    for env in envs.values():
        env.close()


def test_sim_backend_setting_is_validated():
    from adadex.train.config import SimConfig, TrainConfig
    from adadex.train.recipe import train_settings

    assert TrainConfig(dataset="d", out="o").sim == SimConfig("rollout")
    assert train_settings({"dataset": "d", "out": "o", "sim": {"backend": "rollout"}})[0].sim.backend == "rollout"
    with pytest.raises(ConfigError, match=r"sim\.backend.*'rollout', 'warp'"):
        train_settings({"dataset": "d", "out": "o", "sim": {"backend": "jax"}})
    assert TrainConfig(dataset="d", out="o", sim={"backend": "warp"}).sim.backend == "warp"


def test_trainer_envs_take_the_warp_backend(warp, tiny_dataset, tmp_path):
    """``sim.backend=warp`` reaches the trainer's env factory (collection) and its evaluation."""
    from adadex.sim.warp_backend import WarpSim
    from adadex.train.config import CollectorConfig, TrainConfig
    from adadex.train.ppo import PPOTrainer

    cfg = TrainConfig(dataset=str(tiny_dataset), out=str(tmp_path / "run"), randomize=False, wandb=False,
                      progress=False, eval_max_references=0, collector=CollectorConfig(worlds=2),
                      sim={"backend": "warp"})
    env = PPOTrainer(cfg).env_factory(0)()
    assert isinstance(env.base_env.sim, WarpSim)
    env.close()


def test_tracking_env_on_warp_steps_on_the_sims_device(warp, tiny_dataset):
    """With the warp backend the env lives where its worlds do: specs, every output and the step's noise
    are on the sim's device (drawn there from the env's seed: the same seed gives the same rollout, another
    seed another), and TorchRL's spec check passes."""
    import torch
    from torchrl.envs.utils import check_env_specs

    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import TrackingEnv

    def rollout(seed):
        env = TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=seed, backend="warp",
                          randomize=Randomization(proprio_noise=0.01, action_noise_uncorrelated=0.05))
        assert env.device == env.sim.torch_device and env.device.type == torch.device(DEVICE).type
        torch.manual_seed(0)
        td = env.rollout(3)
        devices = {v.device for v in td.values(include_nested=True, leaves_only=True)}
        env.close()
        return td, devices

    a, devices = rollout(1)
    assert devices == {a.device} and a.device.type == torch.device(DEVICE).type
    b, _ = rollout(1)
    c, _ = rollout(2)
    # the same draws; on a GPU MuJoCo Warp's contact sums are not bit-reproducible (atomics): to 1e-4
    torch.testing.assert_close(a["next", "observation"], b["next", "observation"], atol=1e-4, rtol=0)
    assert (a["next", "observation"] - c["next", "observation"]).abs().max() > 1e-3
    env = TrackingEnv(tiny_dataset, num_worlds=2, split=None, backend="warp")
    check_env_specs(env)
    env.close()


@pytest.mark.parametrize("backend", ["rollout", "warp"])
def test_flung_object_resets_its_world_alone(warp, tiny_dataset, backend):
    """An object thrown faster than any tabletop motion marks its world unstable: that world is put back
    at its reference start (step 0) and ends, the other world goes on — on both backends' steps."""
    import torch

    from adadex.envs.tracking import TrackingEnv

    env = TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=0, backend=backend, nthread=0)
    td = env.reset()
    td = env.step(td.set("action", torch.zeros(2, 22, device=env.device)))["next"]
    state = env.sim.state.copy()
    nq = env.sim.models[0].nq
    state[1, 1 + nq + 22] = 20.0          # the object's linear velocity in world 1 (state: time, qpos, qvel …)
    env.sim.set_state(state)
    td = env.step(td.set("action", torch.zeros(2, 22, device=env.device)))["next"]
    unstable = td["privileged", "unstable"].reshape(-1).tolist()
    assert unstable == [False, True] and env.unstable_count == 1
    assert td["privileged", "step"].tolist() == [2, 0] and td["terminated"].reshape(-1).tolist() == [False, True]
    env.close()
