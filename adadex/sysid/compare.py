"""Compare a recording with the model, and say where the model fails.

:func:`compare` replays every sequence and keeps model, measurement and command side by side
(:class:`Comparison`); :func:`localize` turns the errors into findings: joints ranked by error
relative to the sensor-noise floor, regimes (frequency, amplitude, gravity-loaded vs unloaded pose,
windows around velocity reversals) and the worst time windows — as numbers and as sentences.

The noise floor of each joint is estimated from the measurement itself: what a local cubic
(Savitzky–Golay, 9 samples) cannot follow is noise, σ = MAD(q − q_smooth)·1.4826 / ‖e₀ − s‖ with
s the filter's centre row. A model that is right up to the sensor noise is recognized as such.

Example::

    from adadex.sysid.compare import compare, localize
    cmp = compare(recording)
    print(localize(cmp).text)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import savgol_coeffs, savgol_filter

from adadex.sim.patch import ModelPatch

REVERSAL_WINDOW_S = 0.15
#: A joint "fails" when its RMS error exceeds this multiple of its noise floor and this absolute floor.
FAIL_RATIO = 3.0
FAIL_ABS = 2e-3


@dataclass(kw_only=True)
class Comparison:
    """Model vs measurement for one recording under one patch (arrays are (S, T, J)).

    Built by :func:`compare`. ``measured``, ``command`` and ``joint_names`` are the recording's;
    ``error`` is ``simulated − measured``, rad; :meth:`rms` (optionally over ``axis`` and where
    ``mask``), :meth:`rms_per_joint`, :meth:`rms_per_sequence_joint` and :meth:`noise_floor`
    (:func:`noise_floor`) summarize it, and :meth:`summary` gives them as a JSON-ready dict.

    Attributes:
        recording: the :class:`~adadex.data.recording.Recording` compared with.
        patch: the :class:`~adadex.sim.patch.ModelPatch` the model was replayed under.
        simulated: (S, T, J) the model's joint positions, rad, on the recording's sequences, samples
            and joints.

    >>> import numpy as np
    >>> from adadex.sim.patch import ModelPatch
    >>> from adadex.sysid.excite import design_excitation
    >>> plan = design_excitation(["arm_j3"], freqs=(1.0,), amps=(0.5,), poses=("loaded",), kinds=("sine",))
    >>> noisy = plan.command + np.random.default_rng(0).normal(0.0, 1e-3, plan.command.shape)
    >>> cmp = Comparison(recording=plan.to_recording(noisy), patch=ModelPatch(), simulated=plan.command)
    >>> cmp.error.shape, bool(abs(cmp.rms() - 1e-3) < 2e-4)      # a model right up to the sensor noise
    ((1, 181, 1), True)
    """

    recording: object
    patch: ModelPatch
    simulated: np.ndarray

    @property
    def measured(self) -> np.ndarray:
        return self.recording.joint_pos

    @property
    def command(self) -> np.ndarray:
        return self.recording.command

    @property
    def error(self) -> np.ndarray:
        return self.simulated - self.measured

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(self.recording.joint_names)

    def rms(self, axis=None, mask: np.ndarray | None = None) -> np.ndarray:
        e2 = self.error ** 2
        if mask is not None:
            return np.sqrt((e2 * mask).sum(axis=axis) / np.maximum(mask.sum(axis=axis), 1))
        return np.sqrt(e2.mean(axis=axis))

    def rms_per_joint(self) -> np.ndarray:
        return self.rms(axis=(0, 1))

    def rms_per_sequence_joint(self) -> np.ndarray:
        return self.rms(axis=1)

    def noise_floor(self) -> np.ndarray:
        return noise_floor(self.measured)

    def summary(self) -> dict:
        return {
            "patch": self.patch.to_dict(),
            "overall_rms_rad": float(self.rms()),
            "per_joint_rms_rad": dict(zip(self.joint_names, map(float, self.rms_per_joint()))),
            "noise_floor_rad": dict(zip(self.joint_names, map(float, self.noise_floor()))),
            "per_sequence_rms_rad": {lab: dict(zip(self.joint_names, map(float, row)))
                                     for lab, row in zip(self.recording.sequence_labels, self.rms_per_sequence_joint())},
        }


def noise_floor(q: np.ndarray, window: int = 9, order: int = 3) -> np.ndarray:
    """Per-joint sensor-noise estimate (rad) of measured positions (S, T, J)."""
    window = min(window, q.shape[1] - (1 - q.shape[1] % 2))
    if window <= order:
        return np.zeros(q.shape[-1])
    r = q - savgol_filter(q, window, order, axis=1)
    s = savgol_coeffs(window, order)
    e0 = np.zeros(window)
    e0[window // 2] = 1.0
    gain = np.linalg.norm(e0 - s)
    mad = np.median(np.abs(r - np.median(r, axis=1, keepdims=True)), axis=(0, 1))
    return 1.4826 * mad / gain


def heldout_mask(recording) -> np.ndarray:
    """(S,) True for held-out sequences: every third sequence of each excited joint (or overall)."""
    seqs = list(recording.meta.get("sequences") or [{} for _ in range(recording.num_sequences)])
    mask = np.zeros(len(seqs), dtype=bool)
    for joint in {s.get("joint") for s in seqs}:
        own = np.array([i for i, s in enumerate(seqs) if s.get("joint") == joint])
        if own.size >= 3:
            mask[own[2::3]] = True
    return mask


def compare(recording, patch: ModelPatch | None = None, *, replayer=None, nthread: int = 2) -> Comparison:
    """Replay ``recording`` under ``patch`` (default: the nominal model).

    Args:
        recording: the :class:`~adadex.data.recording.Recording` to replay and compare with.
        patch: the effects to add to the model (:class:`~adadex.sim.patch.ModelPatch`); None (default):
            none, the nominal model of the recording's robot.
        replayer: a :class:`~adadex.sysid.replay.Replayer` of this recording to reuse (it keeps the
            models it compiled, so several comparisons replay faster); None (default): a new one.
        nthread: threads of the new replayer's rollout pool (default 2; unused with ``replayer``).

    Returns:
        the :class:`Comparison` of the replayed and the measured positions.
    """
    from adadex.sysid.replay import Replayer

    rep = replayer if replayer is not None else Replayer(recording, nthread=nthread)
    patch = patch if patch is not None else ModelPatch(robot=rep.robot)
    return Comparison(recording=recording, patch=patch, simulated=rep.simulate(patch))


def reversal_mask(command: np.ndarray, dt: float, window_s: float = REVERSAL_WINDOW_S) -> np.ndarray:
    """(S, T, J) True within ``window_s`` of a sign change of the commanded velocity."""
    v = np.gradient(command, dt, axis=1)
    moving = np.abs(v) > 1e-6
    flips = np.zeros_like(moving)
    flips[:, 1:] = (np.sign(v[:, 1:]) != np.sign(v[:, :-1])) & moving[:, 1:] & moving[:, :-1]
    w = min(max(1, int(round(window_s / dt))), (command.shape[1] - 1) // 2)   # a window fits a short recording
    kernel = np.ones(2 * w + 1)
    out = np.apply_along_axis(lambda x: np.convolve(x, kernel, mode="same") > 0, 1, flips.astype(float))
    return out


@dataclass(kw_only=True)
class Localization:
    """Where the model fails: machine-readable findings plus the same in sentences."""

    failing_joints: list[str]
    joints: list[dict]                 # per joint, ranked by error/noise
    worst_windows: list[dict]
    sentences: list[str] = field(default_factory=list)

    @property
    def text(self) -> str:
        return "\n".join(self.sentences)

    def to_dict(self) -> dict:
        return {"failing_joints": self.failing_joints, "joints": self.joints,
                "worst_windows": self.worst_windows, "findings": self.sentences}


def _group_rms(err2: np.ndarray, keys: list, j: int, seq_mask: np.ndarray) -> dict:
    out = {}
    for key in sorted({k for k, m in zip(keys, seq_mask) if m and k is not None}, key=str):
        idx = [i for i, (k, m) in enumerate(zip(keys, seq_mask)) if m and k == key]
        out[key] = float(np.sqrt(err2[idx, :, j].mean()))
    return out


def localize(cmp: Comparison, *, window_s: float = 0.25, top_windows: int = 5) -> Localization:
    """Rank joints, split errors by regime, find the worst windows; see the module docstring.

    A joint fails when its RMS error on the sequences that move it (all of them, if none does) exceeds
    :data:`FAIL_RATIO` × its noise floor and :data:`FAIL_ABS` rad. Errors near velocity reversals are
    those within :data:`REVERSAL_WINDOW_S` of a sign change of the commanded velocity.

    Args:
        cmp: the :class:`Comparison` to judge; the recording's ``meta["sequences"]`` (as
            :func:`~adadex.sysid.excite.design_excitation` writes them) say which joint, frequency,
            amplitude and pose each sequence has; without them every sequence counts for every joint
            and the error is not split by frequency, amplitude or pose.
        window_s: the length of the sliding window the worst windows are found with, s (default 0.25).
        top_windows: how many worst windows to keep, over all failing joints (default 5).

    Returns:
        a :class:`Localization`: ``failing_joints``; ``joints``, one dict per joint ranked by error over
        noise (RMS and noise floor, rad; the error by frequency, amplitude and pose; near reversals and
        elsewhere); ``worst_windows`` (joint, sequence, ``t_start``/``t_end`` in s, RMS in rad, worst
        first, one per failing joint); and the findings in sentences (``.text``).

    >>> import numpy as np
    >>> from adadex.sim.patch import ModelPatch
    >>> from adadex.sysid.excite import design_excitation
    >>> plan = design_excitation(["arm_j3"], freqs=(1.0,), amps=(0.5,), poses=("loaded",), kinds=("sine",))
    >>> noisy = plan.command + np.random.default_rng(0).normal(0.0, 1e-3, plan.command.shape)
    >>> rec = plan.to_recording(noisy)
    >>> localize(Comparison(recording=rec, patch=ModelPatch(), simulated=plan.command)).failing_joints
    []
    >>> loc = localize(Comparison(recording=rec, patch=ModelPatch(), simulated=plan.command + 0.02))
    >>> loc.failing_joints, loc.text.splitlines()[0]                 # 0.02 rad off: ≈ 20 × the noise
    (['arm_j3'], 'The model fails on 1 of 1 joints: arm_j3.')
    """
    rec = cmp.recording
    names = cmp.joint_names
    err2 = cmp.error ** 2
    noise = cmp.noise_floor()
    seqs = list(rec.meta.get("sequences") or [{} for _ in range(rec.num_sequences)])
    # A joint is judged on the sequences that move it: errors a joint shows while another joint
    # moves (a finger shaken by the arm) belong to the moving joint.
    own_masks = []
    for name in names:
        own = np.array([s.get("joint", name) == name for s in seqs])
        own_masks.append(own if own.any() else np.ones(len(seqs), dtype=bool))
    rms = np.array([np.sqrt(err2[m, :, j].mean()) for j, m in enumerate(own_masks)])
    ratio = rms / np.maximum(noise, 1e-6)
    failing = [n for n, r, x in zip(names, rms, ratio) if x > FAIL_RATIO and r > FAIL_ABS]
    rev = reversal_mask(cmp.command, rec.dt)
    joints, sentences = [], []
    order = np.argsort(-ratio)
    for j in order:
        name = names[j]
        own = own_masks[j]
        rev_rms = float(np.sqrt((err2[own, :, j] * rev[own, :, j]).sum() / max(rev[own, :, j].sum(), 1)))
        calm = ~rev[own, :, j]
        calm_rms = float(np.sqrt((err2[own, :, j] * calm).sum() / max(calm.sum(), 1)))
        entry = {
            "joint": name, "rms_rad": float(rms[j]), "noise_rad": float(noise[j]), "error_over_noise": float(ratio[j]),
            "failing": name in failing,
            "by_frequency": _group_rms(err2, [s.get("freq") if s.get("kind") == "sine" else None for s in seqs], j, own),
            "by_amplitude": _group_rms(err2, [round(s["amp"], 3) if s.get("kind") == "sine" else None for s in seqs], j, own),
            "by_pose": _group_rms(err2, [s.get("pose") for s in seqs], j, own),
            "near_reversals_rms_rad": rev_rms, "elsewhere_rms_rad": calm_rms,
        }
        joints.append(entry)
        if name not in failing:
            continue
        words = [f"{name}: RMS error {np.degrees(rms[j]):.2f}° on its own sequences = {ratio[j]:.0f}× its noise floor"]
        if rev_rms > 1.5 * calm_rms:
            words.append(f"{rev_rms / max(calm_rms, 1e-9):.1f}× larger near velocity reversals")
        for key, label, unit in (("by_frequency", "frequency", " Hz"), ("by_amplitude", "amplitude", " rad")):
            g = entry[key]
            if len(g) >= 2:
                ks = sorted(g)
                lo, hi = g[ks[0]], g[ks[-1]]
                trend = "grows" if hi > 1.3 * lo else "shrinks" if lo > 1.3 * hi else "is flat"
                words.append(f"error {trend} with {label} ({ks[0]:g}{unit}: {np.degrees(lo):.2f}° → "
                             f"{ks[-1]:g}{unit}: {np.degrees(hi):.2f}°)")
        g = entry["by_pose"]
        if len(g) == 2 and max(g.values()) > 1.3 * min(g.values()):
            words.append(f"larger in the {max(g, key=g.get)} pose")
        sentences.append("; ".join(words) + ".")
    if not failing:
        sentences.insert(0, "The model matches the measurements to within the sensor noise on every joint.")
    else:
        sentences.insert(0, f"The model fails on {len(failing)} of {len(names)} joints: {', '.join(failing)}.")
    # Worst windows: sliding RMS over window_s on failing joints.
    w = min(max(1, int(round(window_s / rec.dt))), rec.num_steps)
    windows = []
    for name in failing or []:
        j = names.index(name)
        e = np.where(own_masks[j][:, None], err2[:, :, j], 0.0)
        c = np.cumsum(np.pad(e, ((0, 0), (1, 0))), axis=1)
        win = np.sqrt((c[:, w:] - c[:, :-w]) / w)
        s, t0 = np.unravel_index(np.argmax(win), win.shape)
        windows.append({"joint": name, "sequence": rec.sequence_labels[s], "t_start": float(rec.time[t0]),
                        "t_end": float(rec.time[min(t0 + w, rec.num_steps - 1)]), "rms_rad": float(win[s, t0])})
    windows.sort(key=lambda d: -d["rms_rad"])
    for d in windows[:top_windows]:
        sentences.append(f"Worst window: {d['joint']} in {d['sequence']}, t = {d['t_start']:.2f}–{d['t_end']:.2f} s "
                         f"(RMS {np.degrees(d['rms_rad']):.2f}°).")
    return Localization(failing_joints=failing, joints=joints, worst_windows=windows[:top_windows],
                        sentences=sentences)
