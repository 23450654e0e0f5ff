"""Excitation design and synthetic measurements.

:func:`design_excitation` builds per-joint command sequences in the spirit of the paper's
identification (A.2): sinusoid sweeps A·sin(2πft) over frequencies and amplitudes within the joint
limits, plus a linear chirp and a Schroeder-phased multisine, each from a gravity-loaded and an
unloaded arm pose. One joint moves per sequence while the others hold the pose, so errors can be
pinned on joints; every sequence reverses velocity many times, so friction and backlash show.
A smooth 0.25 s ramp starts each sequence from rest. On a user's model (``robot=``, its
:class:`~adadex.sim.model_source.RobotTable`) the sweeps start from the model's home pose
(``poses=("home",)``: its ``home``/first keyframe, else its reference configuration) within its
own joint limits.

:func:`simulate_recording` turns a plan into a :class:`~adadex.data.recording.Recording` by
replaying it on the model plus any effects (a "truth" patch) and adding seeded sensor noise: this
is how tests and demos get data with hidden effects.

Example
-------
>>> from adadex.sysid.excite import design_excitation
>>> plan = design_excitation(["if_pip"], freqs=(1.0,), amps=(0.5,), poses=("loaded",), kinds=("sine",))
>>> plan.command.shape, plan.sequences[0]["kind"]
((1, 181, 1), 'sine')
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from adadex.errors import AdadexError
from adadex.sim.patch import ModelPatch
from adadex.sim.robot import HOME_QPOS, JOINT_NAMES, joint_index, joint_limits

#: Arm poses the sweeps start from. ``loaded``: forearm horizontal, shoulder and elbow carry the
#: arm's weight (≈ 18 and 15 N·m). ``unloaded``: arm straight up, gravity torques near zero.
BASE_POSES: dict[str, np.ndarray] = {}
for _name, (_j3, _j5) in {"loaded": (-1.2, 0.0), "unloaded": (-2.85, 0.0)}.items():
    _q = HOME_QPOS.copy()
    _q[1], _q[2], _q[4] = 0.0, _j3, _j5
    BASE_POSES[_name] = _q

KINDS = ("sine", "chirp", "multisine")
RAMP_S = 0.25


class ExcitationError(AdadexError, ValueError):
    """Bad excitation parameters (unknown joint, kind or pose, non-positive rate or duration)."""


@dataclass(frozen=True, kw_only=True)
class ExcitationPlan:
    """Commands to send: ``command`` (S, T, J) for ``joint_names`` at ``time`` (T,), from ``initial_qpos``.

    Built by :func:`design_excitation`; :meth:`save` writes it as a recording file marked as a plan,
    :meth:`load` / :meth:`from_recording` read one back, and :meth:`to_recording` pairs it with measured
    positions. ``sequence_labels`` are the sequences' ``"label"`` entries.

    Attributes:
        time: (T,) sample times, s, from 0 at a uniform rate.
        joint_names: the J commanded joints (the columns of ``command``), in order.
        command: (S, T, J) joint-position targets, rad: one row of S per sequence.
        initial_qpos: (S, 22) the full configuration each sequence starts from, rad (the model's width
            for a user's model): its pose, including the joints that are not commanded.
        sequences: per sequence, a dict with ``label`` (``"joint/pose/kind/f<freq>/a<fraction>"``),
            ``joint`` (the one joint it moves), ``pose``, ``kind``, ``freq`` (Hz) and ``amp`` (the
            amplitude, rad); a plan read from a recording without them has only ``label``. Default
            ``()``.
        robot: the joint table of the user's model the plan is for
            (:class:`~adadex.sim.model_source.RobotTable`); None (default): adadex's robot.
    """

    time: np.ndarray
    joint_names: tuple[str, ...]
    command: np.ndarray
    initial_qpos: np.ndarray
    sequences: tuple[dict, ...] = field(default_factory=tuple)   # per sequence: joint, pose, kind, freq, amp

    @property
    def sequence_labels(self) -> tuple[str, ...]:
        return tuple(s["label"] for s in self.sequences)

    robot: object = None     # the user model's joint table (None: adadex's robot)

    def to_recording(self, joint_pos: np.ndarray, meta: dict | None = None):
        from adadex.data.recording import Recording

        m = {"sequences": list(self.sequences)}
        m.update(meta or {})
        return Recording(time=self.time, joint_names=self.joint_names, command=self.command,
                         joint_pos=joint_pos, sequence_labels=self.sequence_labels,
                         initial_qpos=self.initial_qpos, meta=m, robot=self.robot)

    def save(self, path) -> None:
        """Save as a recording file whose measured positions equal the commands (marked as a plan)."""
        self.to_recording(self.command.copy(), {"plan": True}).save(path)

    @classmethod
    def from_recording(cls, rec) -> "ExcitationPlan":
        seqs = rec.meta.get("sequences") or [{"label": lab} for lab in rec.sequence_labels]
        return cls(time=rec.time, joint_names=tuple(rec.joint_names), command=rec.command,
                   initial_qpos=rec.initial_qpos, sequences=tuple(seqs), robot=getattr(rec, "robot", None))

    @classmethod
    def load(cls, path, *, robot=None) -> "ExcitationPlan":
        from adadex.data.recording import load_recording

        return cls.from_recording(load_recording(path, robot=robot))


#: the highest frequency of each waveform, in units of its ``freq`` (:func:`_waveform`)
_TOP_HARMONIC = {"sine": 1.0, "chirp": 2.0, "multisine": 2.5}


def _ramp(t: np.ndarray) -> np.ndarray:
    return np.where(t < RAMP_S, 0.5 * (1 - np.cos(np.pi * np.clip(t / RAMP_S, 0, 1))), 1.0)


def _waveform(kind: str, t: np.ndarray, freq: float, duration: float) -> np.ndarray:
    if kind == "sine":
        return np.sin(2 * np.pi * freq * t)
    if kind == "chirp":  # linear sweep from freq/8 to freq·2
        f0, f1 = freq / 8, freq * 2
        return np.sin(2 * np.pi * (f0 * t + 0.5 * (f1 - f0) / duration * t * t))
    if kind == "multisine":  # Schroeder phases keep the crest factor low
        ks = np.arange(1, 6)
        phases = -np.pi * ks * (ks - 1) / len(ks)
        w = sum(np.sin(2 * np.pi * freq * k / 2 * t + p) for k, p in zip(ks, phases))
        return w / np.abs(w).max()
    raise ExcitationError(f"unknown excitation kind {kind!r}; choose from {', '.join(KINDS)}")


def max_amplitude(joint: str, pose: np.ndarray, margin: float = 0.05, robot=None) -> float:
    """Largest amplitude (rad) around ``pose`` that stays ``margin`` inside the joint's limits."""
    j = JOINT_NAMES.index(joint) if robot is None else int(robot.index([joint])[0])
    lo, hi = (joint_limits() if robot is None else robot.limits)[j]
    return float(max(0.0, min(pose[j] - lo, hi - pose[j]) - margin))


def design_excitation(joints, *, freqs=(0.5, 1.5, 3.0), amps=(0.25, 1.0), poses=("loaded", "unloaded"),
                      kinds=KINDS, duration: float = 3.0, rate: float = 60.0,
                      max_amp: float = 0.6, robot=None) -> ExcitationPlan:
    """Per-joint sweeps; see the module docstring.

    ``amps`` are fractions of the joint's largest in-limit amplitude at the pose (capped at
    ``max_amp`` rad); sine sequences cover every (freq, amp, pose), chirp and multisine one per pose
    at the largest amplitude with ``max(freqs)`` as their base frequency ``f``: the chirp sweeps
    linearly from f/8 to 2f, the multisine sums components at f/2, f, …, 5f/2.

    Args:
        joints: the names of the joints to excite, one at a time (at least one; an unknown name raises
            :class:`~adadex.sim.robot.UnknownJointError`). They are the plan's columns, in this order.
        freqs: the sine frequencies, Hz, each in (0, ``rate``/4] (default ``(0.5, 1.5, 3.0)``).
        amps: amplitudes as fractions in (0, 1] of the joint's largest amplitude about the pose that
            stays 0.05 rad inside its limits, capped at ``max_amp`` (default ``(0.25, 1.0)``).
        poses: the poses the sweeps start from: ``"loaded"`` (forearm horizontal, the shoulder and elbow
            hold the arm's weight) and/or ``"unloaded"`` (arm straight up), :data:`BASE_POSES` (the
            default: both). On a user's model the only pose is ``"home"``, and the default becomes
            ``("home",)``.
        kinds: the waveforms, of :data:`KINDS` (default all three): ``"sine"`` (one sequence per
            freq × amp), ``"chirp"`` and ``"multisine"`` (one each, see above). Other names are ignored.
        duration: the length of each sequence, s (> 0.5: twice the 0.25 s starting ramp; default 3).
        rate: the command rate, Hz (> 0; default 60): ``round(duration · rate) + 1`` samples.
        max_amp: the largest amplitude of any sequence, rad (default 0.6).
        robot: the joint table of the user's model to excite
            (:class:`~adadex.sim.model_source.RobotTable`: its joints, limits and home pose); None
            (default) or the built-in table: adadex's robot.

    Returns:
        the :class:`ExcitationPlan`: for each joint, pose and kind (in that order) its sequences, one
        joint moving in each; bad values raise :class:`ExcitationError`.

    >>> plan = design_excitation(["arm_j3"], freqs=(1.0,), amps=(0.5, 1.0), poses=("loaded",))
    >>> plan.command.shape, plan.sequence_labels[-1]          # 2 sines, a chirp, a multisine; 3 s at 60 Hz
    ((4, 181, 1), 'arm_j3/loaded/multisine/f1/a1')
    """
    joints = list(joints)
    if not joints:
        raise ExcitationError("no joints to excite")
    robot = None if robot is None or robot.builtin else robot
    base_poses = BASE_POSES if robot is None else {"home": robot.home}
    if robot is not None and tuple(poses) == ("loaded", "unloaded"):
        poses = ("home",)
    joint_index(joints) if robot is None else robot.index(joints)
    for p in poses:
        if p not in base_poses:
            raise ExcitationError(f"unknown pose {p!r}; choose from {', '.join(base_poses)}")
    for name, values in (("freqs", freqs), ("amps", amps), ("rate", (rate,)), ("duration", (duration,))):
        try:
            bad = [v for v in values if not np.isfinite(float(v))]
        except (TypeError, ValueError):
            raise ExcitationError(f"{name}: expected numbers, got {values!r}") from None
        if bad:
            raise ExcitationError(f"{name}: expected finite numbers, got {bad[0]!r}")
    if not freqs or not amps:
        raise ExcitationError(f"freqs and amps need at least one value each, got freqs={list(freqs)}, amps={list(amps)}")
    if rate <= 0 or duration <= 2 * RAMP_S:
        raise ExcitationError(f"rate must be > 0 and duration > {2 * RAMP_S} s (got rate={rate}, duration={duration})")
    unknown = [k for k in kinds if k not in KINDS]
    if unknown or not kinds:
        raise ExcitationError(f"kinds: unknown excitation kind {unknown[0]!r}; choose from {', '.join(KINDS)}"
                              if unknown else f"kinds: none given; choose from {', '.join(KINDS)}")
    if any(f <= 0 or f > rate / 4 for f in freqs):
        raise ExcitationError(f"frequencies must lie in (0, rate/4 = {rate / 4}] Hz, got {list(freqs)}")
    top = max(freqs) * max(_TOP_HARMONIC[k] for k in kinds)
    if top >= rate / 2:
        raise ExcitationError(f"freqs: the {max(kinds, key=_TOP_HARMONIC.get)} at {max(freqs):g} Hz reaches "
                              f"{top:g} Hz, at or above the Nyquist frequency rate/2 = {rate / 2:g} Hz; "
                              f"lower freqs or raise rate")
    if any(not 0 < a <= 1 for a in amps):
        raise ExcitationError(f"amps are fractions of the in-limit amplitude, in (0, 1], got {list(amps)}")
    t = np.arange(int(round(duration * rate)) + 1) / rate
    env = _ramp(t)
    cmds, inits, seqs = [], [], []
    jidx = joint_index(joints) if robot is None else robot.index(joints)
    for joint in joints:
        j = JOINT_NAMES.index(joint) if robot is None else int(robot.index([joint])[0])
        for pose_name in poses:
            pose = base_poses[pose_name]
            a_max = min(max_amplitude(joint, pose, robot=robot), max_amp)
            combos = []
            if "sine" in kinds:
                combos += [("sine", f, a) for f in freqs for a in amps]
            for k in ("chirp", "multisine"):
                if k in kinds:
                    combos.append((k, max(freqs), max(amps)))
            for kind, f, a in combos:
                full = np.tile(pose, (len(t), 1))
                full[:, j] = pose[j] + a * a_max * env * _waveform(kind, t, f, duration)
                cmds.append(full[:, jidx])
                inits.append(pose.copy())
                seqs.append({"label": f"{joint}/{pose_name}/{kind}/f{f:g}/a{a:g}", "joint": joint,
                             "pose": pose_name, "kind": kind, "freq": float(f), "amp": float(a * a_max)})
    return ExcitationPlan(time=t, joint_names=tuple(joints), command=np.stack(cmds),
                          initial_qpos=np.stack(inits), sequences=tuple(seqs), robot=robot)


def simulate_recording(plan: ExcitationPlan, patch: ModelPatch | None = None, *, noise: float = 0.0,
                       seed: int = 0, nthread: int = 2):
    """Replay ``plan`` on the model + ``patch`` and add N(0, noise²) sensor noise (rad), seeded.

    Args:
        plan: the commands to replay (:class:`ExcitationPlan`), on ``plan.robot``'s model.
        patch: the hidden effects, the "truth" (:class:`~adadex.sim.patch.ModelPatch`); None (default):
            none, the nominal model. It is not written into the recording.
        noise: the standard deviation of the Gaussian noise added to every measured position, rad
            (finite, ≥ 0; default 0: none).
        seed: the noise's random seed (``numpy.random.default_rng``; default 0).
        nthread: threads of the :class:`~adadex.sysid.replay.Replayer`'s rollout pool (default 2).

    Returns:
        a :class:`~adadex.data.recording.Recording` of the plan's commands and the simulated, noisy
        positions; its ``meta`` holds the plan's ``sequences``, ``simulated``, ``noise_rad``, ``seed``
        and the ``model`` id.
    """
    from adadex.sysid.replay import Replayer

    if not (isinstance(noise, (int, float, np.floating, np.integer)) and np.isfinite(noise) and noise >= 0):
        raise ExcitationError(f"noise: the sensor noise std must be a finite number ≥ 0 (rad), got {noise!r}")
    patch = patch if patch is not None else ModelPatch(robot=plan.robot)
    proto = plan.to_recording(plan.command.copy())
    q = Replayer(proto, nthread=nthread).simulate(patch)
    q = q + np.random.default_rng(seed).normal(0.0, noise, size=q.shape)
    # The truth patch is deliberately not recorded: the workbench must find it.
    return plan.to_recording(q, {"simulated": True, "noise_rad": noise, "seed": seed,
                                 "model": patch.model_id if plan.robot is None else plan.robot.model_id})
