"""What every physics backend of :class:`~adadex.sim.batched.BatchedSim` shares: the readout of one
control step, the state layout, the names of the backends and the flung-object check.

Kept apart from :mod:`adadex.sim.batched` so the MuJoCo Warp backend (:mod:`adadex.sim.warp_backend`),
which ``BatchedSim(..., backend="warp")`` builds, imports it without importing ``batched`` back.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from adadex.errors import ConfigError
from adadex.sim.scene import CONTROL_HZ

#: m/s. No tabletop motion moves an object this fast: a faster one means the contact solver pumped
#: energy in (a deep squeeze resolved at once) and the world is treated as unstable by the tracking
#: env (``TrackingConfig.max_object_speed``) and the scripted grasp.
MAX_OBJECT_SPEED = 4.0


def flung(object_vel: np.ndarray, limit: float = MAX_OBJECT_SPEED) -> np.ndarray:
    """(B,) whether each world's object moves faster than ``limit`` (m/s), from ``SimReadout.object_vel``
    (numpy, or a torch tensor on any device)."""
    lin = (object_vel if hasattr(object_vel, "device") else np.asarray(object_vel))[..., :3]
    return (lin * lin).sum(axis=-1) > limit * limit


#: Physics backends of :class:`~adadex.sim.batched.BatchedSim`: C MuJoCo's ``mujoco.rollout`` thread pool on the CPU
#: cores, or MuJoCo Warp (:mod:`adadex.sim.warp_backend`; GPU or Warp's CPU device).
BACKENDS = ("rollout", "warp")


def check_backend(backend: str) -> str:
    """``backend`` if it names a physics backend, else a ConfigError."""
    if backend not in BACKENDS:
        raise ConfigError(f"backend must be one of {', '.join(map(repr, BACKENDS))}, got {backend!r}")
    return backend


FULLPHYSICS = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
CTRL_SPEC = int(mujoco.mjtState.mjSTATE_CTRL)


@dataclass
class SimReadout:
    """What one control step returns, all arrays with the batch dimension first.

    Attributes:
        time: (B,) simulated time of each world, s.
        joint_pos: (B, 22) joint positions, rad.
        joint_vel: (B, 22) joint velocities, rad/s.
        link_pose: (B, 5, 7) palm and the 4 fingertips: world position (m) + wxyz quaternion.
        object_pose: (B, 7) object position (m) + wxyz quaternion; zeros when the scene has no object.
        object_vel: (B, 6) the object's linear (world frame, m/s) and angular (rad/s) velocity; zeros
            without an object.
        unstable: (B,) bool, True where a world's simulation became unstable (diverged).
    """

    time: np.ndarray          # (B,)
    joint_pos: np.ndarray     # (B, 22)
    joint_vel: np.ndarray     # (B, 22)
    link_pose: np.ndarray     # (B, 5, 7) palm + 4 fingertips, position + wxyz quaternion
    object_pose: np.ndarray   # (B, 7); zeros when the scene has no object
    object_vel: np.ndarray    # (B, 6) linear (world) and angular velocity; zeros without an object
    unstable: np.ndarray      # (B,) bool


def hold_command(m: mujoco.MjModel, d: mujoco.MjData, actuators: np.ndarray, command: np.ndarray) -> None:
    """Write ``command`` (one value per actuator in ``actuators``) into ``d`` as a command that has been
    held for a while: ``ctrl``, a filter actuator's activation (the lagged target it has reached) and a
    delayed actuator's whole history buffer (the commands it has yet to apply). A robot at rest holding
    its pose has these; a zero activation or history would instead pull a lagged or delayed servo
    towards 0 rad for its lag or delay after the reset — a jolt no real robot makes."""
    actuators = np.asarray(actuators, dtype=np.int64).reshape(-1)
    command = np.asarray(command, dtype=float).reshape(-1)
    d.ctrl[actuators] = command
    dyn = m.actuator_dyntype[actuators]
    lag = np.flatnonzero((dyn == int(mujoco.mjtDyn.mjDYN_FILTEREXACT)) | (dyn == int(mujoco.mjtDyn.mjDYN_FILTER)))
    if lag.size:
        a = actuators[lag]
        d.act[m.actuator_actadr[a] + m.actuator_actnum[a] - 1] = command[lag]
    for c in np.flatnonzero(m.actuator_history[actuators, 0] > 0):
        n = int(m.actuator_history[actuators[c], 0])
        mujoco.mj_initCtrlHistory(m, d, int(actuators[c]), None, np.full((n, 1), command[c]))


def reset_states(models, data: mujoco.MjData, worlds: np.ndarray, qpos=None, qvel=None, nstate: int = 0,
                 ctrl=None) -> tuple[np.ndarray, np.ndarray]:
    """The full-physics states (``(len(worlds), nstate)``, ``mj_getState``'s layout) and sensor values of
    ``worlds`` reset to ``qpos``/``qvel`` (broadcast over them; default each model's ``qpos0`` and zero
    velocity), computed with C MuJoCo's ``mj_forward`` on ``data`` (sized for every model): what every
    backend's ``reset`` writes into its worlds. ``ctrl`` (broadcast to ``(len(worlds), nu)``; optional):
    the command the worlds have been holding (:func:`hold_command`), so that an actuator with a lag or
    a delay starts from it rather than from 0."""
    m0 = models[0]
    n = len(worlds)
    qpos_b = None if qpos is None else np.broadcast_to(np.asarray(qpos, float), (n, m0.nq))
    qvel_b = None if qvel is None else np.broadcast_to(np.asarray(qvel, float), (n, m0.nv))
    ctrl_b = None if ctrl is None else np.broadcast_to(np.asarray(ctrl, float), (n, m0.nu))
    states = np.empty((n, nstate or mujoco.mj_stateSize(m0, FULLPHYSICS)))
    sens = np.empty((n, m0.nsensordata))
    for j, w in enumerate(worlds):
        m = models[w]
        mujoco.mj_resetData(m, data)
        if qpos_b is not None:
            data.qpos[:] = qpos_b[j]
        if qvel_b is not None:
            data.qvel[:] = qvel_b[j]
        if ctrl_b is not None:
            hold_command(m, data, np.arange(m.nu), ctrl_b[j])
        mujoco.mj_forward(m, data)
        mujoco.mj_getState(m, data, states[j], FULLPHYSICS)
        sens[j] = data.sensordata
    return states, sens


def world_models(models, batch_size: int | None) -> list[mujoco.MjModel]:
    """One model per world: ``models`` (one ``MjModel`` shared by ``batch_size`` worlds, or a sequence of
    one per world), checked as every backend's constructor checks it."""
    if isinstance(models, mujoco.MjModel):
        if batch_size is None or batch_size < 1:
            raise ConfigError(f"batch_size must be a positive integer with a single model, got {batch_size!r}")
        return [models] * batch_size
    out = list(models)
    if not out:
        raise ConfigError("models must not be empty")
    if batch_size is not None and batch_size != len(out):
        raise ConfigError(f"batch_size={batch_size} but {len(out)} models were given")
    return out


def control_substeps(model: mujoco.MjModel, substeps: int | None) -> int:
    """Physics steps per control step: ``substeps``, or as many as make one 12 Hz control step."""
    if substeps is None:
        substeps = max(1, int(round(1.0 / (CONTROL_HZ * model.opt.timestep))))
    if substeps < 1:
        raise ConfigError(f"substeps must be >= 1, got {substeps}")
    return int(substeps)
