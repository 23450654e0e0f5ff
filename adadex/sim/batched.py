"""B worlds of a scene stepped together, one control step at a time, through ``mujoco.rollout``.

``BatchedSim`` keeps the full physics state of every world in one ``(B, nstate)`` array and advances
all worlds by one control step (``substeps`` physics steps with the control held) in a single call
of a persistent :class:`mujoco.rollout.Rollout` thread pool. Readouts — joint positions and
velocities, tracked-link poses, object pose — are slices of the rollout's output arrays: there is
no per-world Python loop on the hot path.

Per-world models are allowed (a list of ``MjModel`` with the same structure, i.e. the same
``MjModel.signature``), so physics parameters can be randomized per world; worlds may even hold
different objects when their scenes are built with ``uniform_layout=True`` (objects padded to the
same number of geoms and meshes). Results do not depend on the thread count: each world is rolled out
independently from its own state (tested).

Unstable worlds: when MuJoCo detects a diverging simulation it resets that world's ``MjData``,
which shows up as a time that did not advance (or as NaN). ``step`` returns a boolean
``unstable`` mask; such a world's state is left as MuJoCo produced it and the caller decides
(a TrackingEnv resets it alone).

Example
-------
>>> import numpy as np
>>> from adadex.sim.scene import build_scene_model, home_state
>>> from adadex.sim.batched import BatchedSim
>>> model = build_scene_model("box_00")
>>> sim = BatchedSim(model, batch_size=4, nthread=2)
>>> qpos, ctrl = home_state(model)
>>> _ = sim.reset(qpos=qpos)
>>> out = sim.step(np.tile(ctrl, (4, 1)))
>>> out.link_pose.shape
(4, 5, 7)
"""

from __future__ import annotations

from collections.abc import Sequence
import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from adadex.errors import ArrayError, ConfigError
from adadex.sim.readout import (  # noqa: F401  (re-exported: the names users import from here)
    BACKENDS, CTRL_SPEC, FULLPHYSICS, MAX_OBJECT_SPEED, SimReadout, check_backend, control_substeps, flung, reset_states,
    world_models)
from adadex.sim.robot import NUM_JOINTS, TRACKED_SITES


class RolloutPool:
    """Owns a persistent ``mujoco.rollout.Rollout`` thread pool, closed with the object."""

    _pool: mj_rollout.Rollout | None = None

    def _open_pool(self, nthread: int) -> mj_rollout.Rollout:
        self._pool = mj_rollout.Rollout(nthread=nthread)
        return self._pool

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


class BatchedSim(RolloutPool):
    """B worlds stepped together; see the module docstring.

    Args:
        models: one ``MjModel`` shared by all worlds, or a sequence of B models of equal sizes.
        batch_size: B (inferred from ``models`` when it is a sequence).
        nthread: threads of the rollout pool (0 runs on the calling thread).
        substeps: physics steps per control step (default: as many as make one 12 Hz control
            step at the model's timestep).
        backend: ``"rollout"`` (this class) or ``"warp"``: ``BatchedSim(..., backend="warp")`` returns a
            :class:`~adadex.sim.warp_backend.WarpSim` with this interface (needs ``pip install
            "adadex[warp]"``; takes ``device``, ``nconmax``, ``njmax``).
        device: the rollout backend runs on the CPU (``None`` or ``"cpu"``).
    """

    def __new__(cls, models=None, batch_size=None, *, backend: str = "rollout", **kwargs):
        """``backend="warp"`` makes a :class:`~adadex.sim.warp_backend.WarpSim` (MuJoCo Warp, same
        interface; ``device``, ``nconmax``, ``njmax`` go to it); ``"rollout"`` (default) this class."""
        check_backend(backend)
        if backend == "warp" and cls is BatchedSim:
            from adadex.sim.warp_backend import WarpSim
            return WarpSim(models, batch_size, **kwargs)
        return super().__new__(cls)

    def __init__(self, models: mujoco.MjModel | Sequence[mujoco.MjModel], batch_size: int | None = None,
                 *, nthread: int = 1, substeps: int | None = None, backend: str = "rollout", device=None):
        if device is not None and str(device) != "cpu":
            raise ConfigError(f"device={device!r}: the rollout backend runs on the CPU; use backend='warp' "
                              f"for another device")
        self._models = world_models(models, batch_size)
        if nthread < 0:
            raise ConfigError(f"nthread must be >= 0, got {nthread}")
        m0 = self._models[0]
        substeps = control_substeps(m0, substeps)
        self.nstate = mujoco.mj_stateSize(m0, FULLPHYSICS)
        for i, m in enumerate(self._models[1:], start=1):
            # The thread-local MjData are sized for model 0, so structure must match exactly.
            if m.signature != m0.signature:
                raise ConfigError(f"model {i} differs in structure from model 0 (signature {m.signature} "
                                  f"!= {m0.signature}); per-world models may differ only in parameters")
        self.batch_size = len(self._models)
        self.nthread = nthread
        self.substeps = substeps
        self.timestep = float(m0.opt.timestep)
        self._has_object = m0.nq > NUM_JOINTS
        # Equal signatures leave some MjData sizes free: the sparse inertia (an object whose inertia is
        # diagonal in its body frame has a sparser one) and the mesh bounding-volume hierarchies.
        # Size the shared MjData for the largest model.
        self._datas = self._make_datas(self._models)
        self._open_pool(nthread)
        B, nu = self.batch_size, m0.nu
        self.state = np.zeros((B, self.nstate))
        self._ctrl = np.zeros((B, substeps, nu))
        self._state_out = np.empty((B, substeps, self.nstate))
        self._sens_out = np.empty((B, substeps, m0.nsensordata))
        # Offsets of the readouts inside the state and sensor vectors.
        self._qpos0 = 1                      # state = [time, qpos, qvel, act, ...]
        self._qvel0 = 1 + m0.nq
        adr = [int(m0.sensor_adr[m0.sensor(f"{s}_pos").id]) for s in TRACKED_SITES]
        qadr = [int(m0.sensor_adr[m0.sensor(f"{s}_quat").id]) for s in TRACKED_SITES]
        self._link_idx = np.array([list(range(a, a + 3)) + list(range(q, q + 4)) for a, q in zip(adr, qadr)])
        self._last_sens = np.zeros((B, m0.nsensordata))
        self.reset()

    @property
    def models(self) -> list[mujoco.MjModel]:
        return self._models

    @staticmethod
    def _size_key(m: mujoco.MjModel) -> tuple[int, int, int]:
        return (m.nC, m.nbvh, m.nbvhdynamic)

    def _make_datas(self, models) -> list[mujoco.MjData]:
        """Thread-local MjData sized for every model: from the largest one, which must cover all."""
        big = max(models, key=self._size_key)
        key = self._size_key(big)
        for m in models:
            if any(a > b for a, b in zip(self._size_key(m), key)):
                raise ConfigError(f"no single model bounds the data sizes (nC, nbvh, nbvhdynamic) of all worlds: "
                                  f"{self._size_key(m)} vs {key}")
        self._data_key = key
        return [mujoco.MjData(big) for _ in range(max(1, self.nthread))]

    def set_models(self, worlds: Sequence[int], models: Sequence[mujoco.MjModel]) -> None:
        """Give ``worlds`` new models (same structure: another object of a uniform-layout scene, or
        re-randomized parameters). Reset those worlds afterwards; their state is not converted."""
        worlds = [int(w) for w in worlds]
        models = list(models)
        if len(worlds) != len(models):
            raise ConfigError(f"{len(worlds)} worlds but {len(models)} models")
        sig = self._models[0].signature
        for w, m in zip(worlds, models):
            if not 0 <= w < self.batch_size:
                raise IndexError(f"world {w} out of range for batch_size={self.batch_size}")
            if m.signature != sig:
                raise ConfigError(f"model for world {w} differs in structure (signature {m.signature} != {sig}); "
                                  f"build scenes with uniform_layout=True to swap objects")
        for w, m in zip(worlds, models):
            self._models[w] = m
        if any(a > b for m in models for a, b in zip(self._size_key(m), self._data_key)):
            self._datas = self._make_datas(self._models)

    # ---------------------------------------------------------------- state

    def reset(self, qpos: np.ndarray | None = None, qvel: np.ndarray | None = None,
              worlds: np.ndarray | Sequence[int] | None = None, ctrl: np.ndarray | None = None) -> SimReadout:
        """Reset some worlds (all by default) to ``qpos``/``qvel`` (broadcast over the reset worlds).

        Positions default to each model's ``qpos0``, velocities to zero. Sensors are recomputed
        with ``mj_forward`` for the reset worlds only (a reset is not the hot path).
        ``ctrl`` (optional, broadcast over the reset worlds): the command the worlds have been holding,
        written into the activations and history buffers of lagged and delayed actuators too
        (:func:`~adadex.sim.readout.hold_command`), so that their servos start from it, not from 0.
        """
        idx = np.arange(self.batch_size) if worlds is None else np.asarray(worlds, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.batch_size):
            raise IndexError(f"world indices {idx.tolist()} out of range for batch_size={self.batch_size}")
        states, sens = reset_states(self._models, self._datas[0], idx, qpos, qvel, self.nstate, ctrl)
        self.state[idx] = states
        self._last_sens[idx] = sens
        return self.readout()

    def set_state(self, state: np.ndarray, worlds=None) -> None:
        """Overwrite full-physics states (``(B, nstate)`` or ``(len(worlds), nstate)``)."""
        idx = slice(None) if worlds is None else np.asarray(worlds, dtype=np.int64)
        self.state[idx] = state

    # ---------------------------------------------------------------- stepping

    def step(self, ctrl: np.ndarray) -> SimReadout:
        """Advance every world by one control step with ``ctrl`` (B, nu) held constant."""
        ctrl = np.asarray(ctrl, dtype=np.float64)
        if ctrl.shape != (self.batch_size, self._ctrl.shape[2]):
            raise ArrayError(f"ctrl must have shape {(self.batch_size, self._ctrl.shape[2])}, got {ctrl.shape}")
        self._ctrl[:] = ctrl[:, None, :]
        t_expected = self.state[:, 0] + self.substeps * self.timestep
        self._pool.rollout(self._models, self._datas, self.state, self._ctrl, control_spec=CTRL_SPEC,
                           skip_checks=True, nstep=self.substeps, state=self._state_out,
                           sensordata=self._sens_out)
        self.state[:] = self._state_out[:, -1]
        self._last_sens[:] = self._sens_out[:, -1]
        out = self.readout()
        out.unstable |= np.abs(self.state[:, 0] - t_expected) > 0.5 * self.timestep
        return out

    def readout(self) -> SimReadout:
        """Current readouts of all worlds, computed from the state and sensor arrays."""
        nq = self._models[0].nq
        qpos = self.state[:, self._qpos0:self._qpos0 + nq]
        qvel = self.state[:, self._qvel0:self._qvel0 + self._models[0].nv]
        if self._has_object:
            obj = qpos[:, NUM_JOINTS:NUM_JOINTS + 7].copy()
            obj_vel = qvel[:, NUM_JOINTS:NUM_JOINTS + 6].copy()
        else:
            obj = np.zeros((self.batch_size, 7))
            obj_vel = np.zeros((self.batch_size, 6))
        unstable = ~np.isfinite(self.state).all(axis=1)
        return SimReadout(
            time=self.state[:, 0].copy(),
            joint_pos=qpos[:, :NUM_JOINTS].copy(),
            joint_vel=qvel[:, :NUM_JOINTS].copy(),
            link_pose=self._last_sens[:, self._link_idx],
            object_pose=obj,
            object_vel=obj_vel,
            unstable=unstable,
        )
