"""Replay recorded commands on the model: what would the simulator have measured?

Every sequence of a recording is rolled out with ``mujoco.rollout`` (batched over sequences, on a
persistent thread pool), from the recording's initial configuration, first holding the initial
command for :data:`PREROLL_S` so the robot is at rest at t = 0, then with the commands held
constant between samples. The physics step divides the recording period: ``k`` substeps of
``dt_rec / k`` with the smallest ``k`` giving a step ≤ the model's own step (the built-in scene's
:data:`PHYSICS_TIMESTEP`).

The model is the built-in scene or a user's MJCF (``model=``, a
:class:`~adadex.sim.model_source.ModelSource`; default: the recording's own model), used with its
own options and contacts; recorded joints, initial positions and commands map to its servoed
joints by name, and the other actuators are sent 0.

:meth:`Replayer.simulate_imposed` replays with some joints moved exactly as measured (the diagnosis' test
of a knock-on: does a joint's error vanish when the joints that move it follow their measurement?).

A :class:`Replayer` compiles one model per *structure* (which actuators carry a delay buffer or a
lag state) and re-uses it: evaluating a new patch only rewrites model parameters (absolute values
from a snapshot), which is what makes fitting fast.

Example::

    from adadex.sysid.replay import Replayer
    sim = Replayer(recording).simulate()   # the nominal model
    sim.shape == recording.joint_pos.shape
"""

from __future__ import annotations

import copy
import dataclasses
import math

import mujoco
import numpy as np

from adadex.sim.batched import RolloutPool
from adadex.sim.effects import ModelBase, robot_ids
from adadex.sim.model_source import ModelSource, same_model
from adadex.sim.patch import ModelPatch, patched_scene
from adadex.sim.readout import CTRL_SPEC, FULLPHYSICS, hold_command
from adadex.sim.scene import PHYSICS_TIMESTEP, PhysicsOptions

#: Before t = 0 the robot holds the first command for this long, as a real robot does before a
#: recording starts: every sequence then starts at rest at the model's own equilibrium (a weaker
#: servo or a payload sags before the first sample, not during it).
PREROLL_S = 0.5
#: :meth:`Replayer.simulate_imposed` drives a joint along its measured path as a flywheel of this many times
#: the model's largest joint-space inertia: whatever else acts on it moves it by a part in this many
IMPOSED_INERTIA = 1e8
QFRC_APPLIED_SPEC = int(mujoco.mjtState.mjSTATE_QFRC_APPLIED)


def substeps_for(dt: float, max_step: float = PHYSICS_TIMESTEP) -> int:
    """Smallest k with dt / k ≤ max_step (+ a 1e-9 relative tolerance)."""
    return max(1, math.ceil(dt / max_step * (1 - 1e-9)))


class Replayer(RolloutPool):
    """Replays one recording under any number of patches; see the module docstring.

    Args:
        recording: a :class:`adadex.data.recording.Recording`.
        nthread: threads of the rollout pool.
        preroll_s: how long, s, the robot holds the first command before ``time[0]``, so every sequence
            starts at rest at the model's own equilibrium (default :data:`PREROLL_S`).
        model: the model to replay on (default: the recording's model, the built-in scene unless the
            recording was loaded with a user model's joint table).
    """

    def __init__(self, recording, *, nthread: int = 2, preroll_s: float = PREROLL_S,
                 model: ModelSource | None = None):
        rec_robot = getattr(recording, "robot", None)
        self.source = model if model is not None else (rec_robot.source if rec_robot is not None else ModelSource())
        self.robot = self.source.robot()
        if not same_model(self.robot.model_id, rec_robot.model_id if rec_robot is not None else None):
            # Read the recording's joints as the model's (same names and columns, else a RecordingError).
            recording = dataclasses.replace(recording, robot=self.robot)
        self.rec = recording
        self.nthread = nthread
        self.k = substeps_for(recording.dt, self.source.timestep)
        self.timestep = recording.dt / self.k
        self.jid = np.asarray(recording.joint_indices)
        self._models: dict[tuple, tuple[mujoco.MjModel, ModelBase, list[mujoco.MjData]]] = {}
        self._open_pool(nthread)
        self._command = np.asarray(recording.full_command(), dtype=np.float64)   # (S, T, J_robot)
        S, T, _ = self._command.shape
        self.num_steps = (T - 1) * self.k
        self.preroll_steps = int(round(preroll_s / self.timestep))

    # ------------------------------------------------------------------ models

    @staticmethod
    def _structure_key(patch: ModelPatch) -> tuple:
        return tuple(sorted((e.effect, j) for e in patch.active().effects if e.spec.stage == "structure"
                            for j, v in zip(e.joints, e.values) if not e.spec.is_absent(v)))

    def model_for(self, patch: ModelPatch) -> tuple[mujoco.MjModel, ModelBase, list[mujoco.MjData]]:
        """The compiled model with ``patch``'s structure, its parameters set to ``patch``."""
        key = self._structure_key(patch)
        if patch.effects:
            patch.check_model(self.robot.model_id)
        if key not in self._models:
            # Compiled with the structural effects only, so the snapshot holds the nominal parameters
            # (the structural effects' own parameters are set absolutely, whatever the snapshot says);
            # a copy, as this model's parameters are rewritten for every patch evaluated. The built-in
            # scene comes from the one patched-scene builder (cached); a user's MJCF from its source.
            if self.source.builtin:
                model = copy.copy(patched_scene(None, patch.stage("structure"),
                                                options=PhysicsOptions(timestep=self.timestep)))
            else:
                spec = self.source.spec(self.timestep)
                patch.stage("structure").edit_spec(spec)
                model = spec.compile()
            self._models[key] = (model, ModelBase.of(model), [mujoco.MjData(model) for _ in range(max(1, self.nthread))])
        model, base, datas = self._models[key]
        base.restore(model)
        patch.apply_model(model, base)
        return model, base, datas

    # ------------------------------------------------------------------ simulation

    def _initial_states(self, model: mujoco.MjModel, command0: np.ndarray, seq_idx: np.ndarray) -> np.ndarray:
        S = command0.shape[0]
        nstate = mujoco.mj_stateSize(model, FULLPHYSICS)
        out = np.empty((S, nstate))
        d = mujoco.MjData(model)
        jnt, _, act = robot_ids(model, np.arange(self.robot.num_joints))
        qadr = model.jnt_qposadr[jnt]
        q0 = np.asarray(self.rec.initial_qpos)[seq_idx]
        for s in range(S):
            mujoco.mj_resetData(model, d)
            d.qpos[qadr] = q0[s]
            hold_command(model, d, act, command0[s])
            mujoco.mj_forward(model, d)
            mujoco.mj_getState(model, d, out[s], FULLPHYSICS)
        return out

    def simulate(self, patch: ModelPatch | None = None, *, sequences=None, full: bool = False) -> np.ndarray:
        """Simulated joint positions, (S, T, J) for the recording's joints (``full``: all the robot's).

        ``sequences`` restricts the replay to some sequence indices (fitting uses this to replay
        only the sequences that excite the joints being fitted).
        """
        patch = patch if patch is not None else ModelPatch(robot=self.robot)
        model, _, datas = self.model_for(patch)
        idx = np.arange(self._command.shape[0]) if sequences is None else np.asarray(sequences, dtype=np.int64)
        cmd = patch.transform_command(self._command[idx], self.rec.dt)
        S, T, _ = cmd.shape
        init = self._initial_states(model, cmd[:, 0], idx)
        P = self.preroll_steps
        ctrl = np.concatenate([np.repeat(cmd[:, :1], P, axis=1), np.repeat(cmd[:, :-1], self.k, axis=1)], axis=1)
        jnt, _, act = robot_ids(model, np.arange(self.robot.num_joints))
        state = self._rollout(model, datas, init, ctrl, act)
        cols = 1 + model.jnt_qposadr[jnt]          # a FULLPHYSICS state is time, qpos, qvel, …
        qpos = np.empty((S, T, len(jnt)))
        qpos[:, 0] = state[:, P - 1, cols] if P else init[:, cols]
        qpos[:, 1:] = state[:, P + self.k - 1::self.k][..., cols]
        qpos = patch.transform_measurement(qpos)
        return qpos if full else qpos[..., self.jid]

    def simulate_windows(self, patch: ModelPatch | None = None, *, length: int, sequences=None) -> np.ndarray:
        """Multiple shooting: simulated joint positions (S, T, J) of the recording's joints, as
        :meth:`simulate`, but with the simulation restarted from the measurement every ``length``
        samples — each sample is predicted from the measured positions at most ``length`` samples
        earlier.

        At each window's first sample the recorded joints' positions are set to the measured ones (as
        the joints were before the patch's sensor effects: an encoder offset is additive, so it is undone
        exactly) and, when the recording has ``joint_vel``, their velocities to the measured ones; all
        else — the recorded joints' velocities otherwise, actuator delay buffers, lag activations,
        joints not recorded, objects — is carried over from the end of the window before, so the state
        that cannot be measured follows the measured motion (the fingers of an arm swung fast stay with
        the arm). The velocity is the model's own, not a finite difference of the measured positions:
        with commands held between samples the servo's transients within one sample make a (smoothed)
        difference of 60-Hz positions miss the velocity by ~10 % of its RMS, enough to bury a small
        friction's effect in each window's start. All sequences are rolled out together, window after
        window; the first window starts at the end of the pre-roll."""
        patch = patch if patch is not None else ModelPatch(robot=self.robot)
        idx = np.arange(self._command.shape[0]) if sequences is None else np.asarray(sequences, dtype=np.int64)
        model, _, datas = self.model_for(patch)
        cmd = patch.transform_command(self._command[idx], self.rec.dt)
        S, T, _ = cmd.shape
        jnt, _, act = robot_ids(model, np.arange(self.robot.num_joints))
        qcols, vcols = 1 + model.jnt_qposadr[jnt], 1 + model.nq + model.jnt_dofadr[jnt]
        state = self._initial_states(model, cmd[:, 0], idx)
        P = self.preroll_steps
        if P:
            state = self._rollout(model, datas, state, np.repeat(cmd[:, :1], P, axis=1), act)[:, -1]
        qpos = np.empty((S, T, len(jnt)))
        qpos[:, 0] = state[:, qcols]
        # the measured positions as the joints were (the sensor effects undone: exact for offsets)
        q = np.repeat(qpos[:, :1], T, axis=1)
        q[..., self.jid] = self.rec.joint_pos[idx]
        q = 2 * q - patch.transform_measurement(q.copy())
        L = max(1, int(length))
        for t0 in range(0, T - 1, L):
            n = min(L, T - 1 - t0)
            state = state.copy()
            state[:, qcols[self.jid]] = q[:, t0, self.jid]
            if self.rec.joint_vel is not None:
                state[:, vcols[self.jid]] = np.asarray(self.rec.joint_vel)[idx, t0]
            states = self._rollout(model, datas, state, np.repeat(cmd[:, t0:t0 + n], self.k, axis=1), act)
            qpos[:, t0 + 1:t0 + n + 1] = states[:, self.k - 1::self.k][..., qcols]
            state = states[:, -1]
        return patch.transform_measurement(qpos)[..., self.jid]

    def simulate_imposed(self, patch: ModelPatch | None = None, *, imposed, sequences=None) -> np.ndarray:
        """Simulated joint positions (S, T, J) of the recording's joints, as :meth:`simulate`, with the
        joints ``imposed`` (names or columns of the recording's joints) moved exactly as measured: what the
        model says the other joints do when those follow their measured path, whatever moves them.

        Each imposed joint is made a flywheel driven along the measurement: its armature is raised by
        :data:`IMPOSED_INERTIA` × the model's largest joint-space inertia, and a generalized force on it
        of that added armature × the acceleration that brings the integrator exactly onto the measured
        path at every physics step (the second difference of the measured positions, cubic-spline
        interpolated to the physics steps; held at the first sample through the pre-roll). Whatever else
        acts on it — its servo, a missing effect, the reaction of the joints it carries — changes its
        acceleration by a part in :data:`IMPOSED_INERTIA`, so it moves as measured (to 1e-8 rad RMS on the
        tiny arm of the tests) while every other joint feels its measured motion through the model's own
        coupled dynamics (its inertia coupling, Coriolis and gravity terms), with the model's integrator.
        One rollout, as :meth:`simulate`; the diagnosis uses it to tell a knock-on from a source. The sensor effects
        of ``patch`` are undone on the measured path first (exactly for an encoder offset, as in
        :meth:`simulate_windows`). Only hinge and slide joints can be imposed."""
        from scipy.interpolate import CubicSpline

        patch = patch if patch is not None else ModelPatch(robot=self.robot)
        idx = np.arange(self._command.shape[0]) if sequences is None else np.asarray(sequences, dtype=np.int64)
        names = list(self.rec.joint_names)
        cols = np.array([names.index(j) if isinstance(j, str) else int(j) for j in imposed], dtype=np.int64)
        model, _, datas = self.model_for(patch)
        cmd = patch.transform_command(self._command[idx], self.rec.dt)
        S, T, _ = cmd.shape
        jnt, _, act = robot_ids(model, np.arange(self.robot.num_joints))
        qcols = 1 + model.jnt_qposadr[jnt]
        ejnt = jnt[self.jid[cols]]
        if np.any((model.jnt_type[ejnt] != mujoco.mjtJoint.mjJNT_HINGE)
                  & (model.jnt_type[ejnt] != mujoco.mjtJoint.mjJNT_SLIDE)):
            raise ValueError("only hinge and slide joints can be imposed")
        edof = model.jnt_dofadr[ejnt]
        # the measured path of the imposed joints, as the joints were (sensor effects undone), at every
        # physics step: the pre-roll holds the first sample, then a cubic spline through the samples
        q = np.zeros((S, T, self.robot.num_joints))
        q[..., self.jid] = self.rec.joint_pos[idx]
        q = (2 * q - patch.transform_measurement(q.copy()))[..., self.jid[cols]]       # (S, T, E)
        P, h = self.preroll_steps, self.timestep
        tt = np.arange((T - 1) * self.k + 1) * h
        path = CubicSpline(np.arange(T) * self.rec.dt, q, axis=1)(np.minimum(tt, (T - 1) * self.rec.dt))
        path = np.concatenate([np.repeat(path[:, :1], P + 1, axis=1), path[:, 1:]], axis=1)   # (S, N+1, E)
        # semi-implicit Euler from rest (v' = v + h a, q' = q + h v'): a_i = (Q[i+1] - 2 Q[i] + Q[i-1]) / h²
        prev = np.concatenate([path[:, :1], path[:, :-2]], axis=1)
        accel = (path[:, 1:] - 2 * path[:, :-1] + prev) / h ** 2                          # (S, N, E)
        init = self._initial_states(model, cmd[:, 0], idx)
        init[:, qcols[self.jid[cols]]] = q[:, 0]
        init[:, 1 + model.nq + edof] = 0.0
        ctrl = np.concatenate([np.repeat(cmd[:, :1], P, axis=1), np.repeat(cmd[:, :-1], self.k, axis=1)], axis=1)
        n = ctrl.shape[1]
        armature = model.dof_armature.copy()
        try:
            d = mujoco.MjData(model)
            mujoco.mj_setState(model, d, init[0], FULLPHYSICS)
            mujoco.mj_forward(model, d)
            inertia = np.zeros((model.nv, model.nv))
            mujoco.mj_fullM(model, d, inertia)
            big = IMPOSED_INERTIA * float(max(np.max(np.diag(inertia)), 1e-9))
            model.dof_armature[edof] = armature[edof] + big
            force = np.zeros((S, n, model.nv))
            force[..., edof] = big * accel
            controls = np.concatenate([_model_ctrl(model, act, ctrl), force], axis=2)
            state = np.empty((S, n, init.shape[1]))
            self._pool.rollout([model] * S, datas, np.ascontiguousarray(init), np.ascontiguousarray(controls),
                               control_spec=CTRL_SPEC | QFRC_APPLIED_SPEC, skip_checks=True, nstep=n,
                               state=state, sensordata=np.empty((S, n, model.nsensordata)))
        finally:
            model.dof_armature[:] = armature
        out = np.empty((S, T, len(jnt)))
        out[:, 0] = state[:, P - 1, qcols] if P else init[:, qcols]
        out[:, 1:] = state[:, P + self.k - 1::self.k][..., qcols]
        return patch.transform_measurement(out)[..., self.jid]

    def _rollout(self, model, datas, init: np.ndarray, ctrl: np.ndarray, act: np.ndarray) -> np.ndarray:
        """The states (S, n, nstate) of ``init`` (S, nstate) driven by ``ctrl`` (S, n, J_robot)."""
        S, n = ctrl.shape[:2]
        state = np.empty((S, n, init.shape[1]))
        self._pool.rollout([model] * S, datas, np.ascontiguousarray(init), _model_ctrl(model, act, ctrl),
                           control_spec=CTRL_SPEC, skip_checks=True, nstep=n, state=state,
                           sensordata=np.empty((S, n, model.nsensordata)))
        return state


def _model_ctrl(model: mujoco.MjModel, act: np.ndarray, ctrl: np.ndarray) -> np.ndarray:
    """``ctrl`` (…, J_robot) as the model's controls (…, nu), contiguous: the other actuators are sent 0."""
    if not np.array_equal(act, np.arange(model.nu)):
        full_ctrl = np.zeros(ctrl.shape[:-1] + (model.nu,))
        full_ctrl[..., act] = ctrl
        ctrl = full_ctrl
    return np.ascontiguousarray(ctrl)
