"""Instruction-driven synthesis of human hand–object motion, noisy on purpose.

adadex has no text-to-motion model; this module produces the same kind of data one would: an
instruction (a verb with parameters, e.g. "lift the mug 15 cm") becomes an object trajectory and a
human hand motion — approach from afar, pre-shape, grasp at contact points chosen on the object's
surface, manipulate, release, retreat — and each base instruction has paraphrases that change the
text and the motion (speed, timing, path curvature, approach direction, grasp choice). A base
instruction and its paraphrases form one *semantic group*.

Like generated motion, the result is imperfect, and :class:`NoiseConfig` controls how: per-frame
jitter, slow drift of the hand relative to the object, fingertips that sink into the object,
contact timing errors (the object moves before the hand has closed, or after), and a human hand
whose proportions differ from the robot's (embodiment bias, see :mod:`adadex.data.human_hand`).
Every random choice comes from one seed: the same seed gives the same motion, bit for bit.

Coordinates: world frame, robot base at the origin, table top at z = 0; frames at ``fps`` (12 Hz,
one per control step).

Example
-------
>>> from adadex.data.synth import Synthesizer, make_instruction
>>> instr = make_instruction("lift", "cube_050", seed=0)
>>> instr.text
'lift the cube 19 cm'
>>> variants = Synthesizer().paraphrases(instr, 3, seed=0)
>>> motion = Synthesizer().synthesize(variants[1], seed=1)
>>> motion.keypoints.shape[1:], motion.object_pose.shape[1]
((21, 3), 7)
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Slerp

from adadex.data.human_hand import ANGLE_LIMITS, NUM_ANGLES, TIP_INDEX, HumanHand
from adadex.errors import ConfigError, check_numbers
from adadex.geometry import Rotation, compose, first_hits, inverse, quat, rotation, slerp_poses
from adadex.sim.objects import get_object
from adadex.sim.scene import CONTROL_HZ, OBJECT_HOME_XY, REST_GAP

VERBS = ("lift", "place", "move", "rotate", "pour", "push", "flip", "shake", "reorient", "handover")

#: Text templates per verb; ``{obj}`` is the object's category, the rest are instruction parameters.
TEMPLATES: dict[str, tuple[str, ...]] = {
    "lift": ("lift the {obj} {h_cm} cm", "pick up the {obj} and raise it about {h_cm} centimetres",
             "raise the {obj} {h_cm} cm off the table, then set it back", "hold the {obj} up {h_cm} cm high",
             "take the {obj} and lift it by {h_cm} cm"),
    "place": ("place the {obj} {d_cm} cm to the {side}", "move the {obj} over to the {side} by {d_cm} cm",
              "pick up the {obj} and put it down {d_cm} cm {side}ward", "set the {obj} {d_cm} cm further {side}"),
    "move": ("move the {obj} along a curve to the {side}", "carry the {obj} around to the {side}",
             "bring the {obj} over to the {side} in an arc", "transport the {obj} {side}wards along a bend"),
    "rotate": ("rotate the {obj} by {deg} degrees", "turn the {obj} {deg} degrees about its vertical axis",
               "spin the {obj} around by {deg} degrees", "twist the {obj} {deg} degrees and put it down"),
    "pour": ("pour from the {obj} to the {side}", "tip the {obj} {deg} degrees as if pouring",
             "tilt the {obj} over to the {side} to pour", "empty the {obj} by tilting it {deg} degrees"),
    "push": ("push the {obj} {d_cm} cm", "slide the {obj} {d_cm} cm across the table",
             "shove the {obj} {d_cm} centimetres", "drag the {obj} {d_cm} cm along the table"),
    "flip": ("flip the {obj} over by {deg} degrees", "turn the {obj} onto its side",
             "tip the {obj} over", "roll the {obj} {deg} degrees and set it down"),
    "shake": ("shake the {obj}", "shake the {obj} {n} times", "lift the {obj} and shake it",
              "wave the {obj} back and forth"),
    "reorient": ("reorient the {obj} in hand by {deg} degrees", "turn the {obj} {deg} degrees between your fingers",
                 "rotate the {obj} in the hand", "roll the {obj} {deg} degrees within the grasp"),
    "handover": ("hand the {obj} over to the {side}", "pass the {obj} across to the {side}",
                 "give the {obj} to someone on the {side}", "lift the {obj} high and move it to the {side}"),
}

# Reachable area for object placements (m, world x and y).
_X_RANGE, _Y_RANGE = (0.32, 0.62), (-0.32, 0.32)


@dataclass(frozen=True)
class NoiseConfig:
    """How imperfect the synthesized motion is (all zero = clean). Lengths in m, times in s.

    Attributes:
        jitter: std of the per-frame Gaussian noise on keypoints and object position, m (default 0.002).
        jitter_rot: per-frame object rotation noise, rad (default 0.01).
        drift: amplitude of a slow random drift of the hand against the object, m (default 0.01).
        penetration: fingertips end up to this deep inside the object, m (default 0.008).
        contact_timing: std of the offset between the hand's grasp/release and the object's
            motion, s (default 0.25).
        proportion: relative std of per-finger bone lengths (embodiment bias; default 0.08).
        hand_size: relative std of the overall hand size (default 0.05).

    Examples:
        >>> NoiseConfig.clean().jitter, NoiseConfig().jitter
        (0.0, 0.002)
    """

    jitter: float = 0.002           # per-frame Gaussian noise on keypoints and object position
    jitter_rot: float = 0.01        # per-frame object rotation noise, rad
    drift: float = 0.01             # amplitude of a slow random drift of the hand against the object
    penetration: float = 0.008      # fingertips end up to this deep inside the object
    contact_timing: float = 0.25    # std of the offset between the hand's grasp/release and object motion
    proportion: float = 0.08        # relative std of per-finger bone lengths (embodiment bias)
    hand_size: float = 0.05         # relative std of the overall hand size

    @classmethod
    def clean(cls) -> NoiseConfig:
        return cls(**{k: 0.0 for k in asdict(cls())})

    def __post_init__(self):
        check_numbers("NoiseConfig", self, asdict(self))


@dataclass(frozen=True)
class Instruction:
    """A verb with parameters on one object, its text, and how the motion is performed.

    ``style`` holds the paraphrase's motion choices: ``speed`` (×), ``curvature`` (m of sideways
    bulge on transport paths), ``approach_yaw`` (rad, where the hand comes from), ``grasp`` (index
    of the grasp candidate), ``timing`` (per-phase duration factors).
    """

    verb: str
    object_name: str
    params: dict
    text: str
    paraphrase: int = 0
    style: dict = field(default_factory=lambda: {"speed": 1.0, "curvature": 0.0, "approach_yaw": 0.0,
                                                  "grasp": 0, "timing": 1.0})


@dataclass
class HumanMotion:
    """A synthesized motion: human keypoints and the object's trajectory, per frame."""

    instruction: Instruction
    keypoints: np.ndarray       # (T, 21, 3)
    object_pose: np.ndarray     # (T, 7)
    wrist_pose: np.ndarray      # (T, 7)
    angles: np.ndarray          # (T, 20)
    fps: float
    phases: dict                # phase name → first frame
    meta: dict


def _category(name: str) -> str:
    return get_object(name).category.replace("_", " ")


def make_instruction(verb: str, object_name: str, seed: int) -> Instruction:
    """A base instruction: ``verb`` on ``object_name`` with parameters drawn from ``seed``."""
    if verb not in VERBS:
        raise ConfigError(f"unknown verb {verb!r}; expected one of {VERBS}")
    get_object(object_name)  # raises UnknownObjectError with suggestions
    rng = np.random.default_rng([seed, VERBS.index(verb)])
    side = str(rng.choice(["left", "right"]))
    sign = 1.0 if side == "left" else -1.0
    p: dict = {"x0": float(rng.uniform(-0.06, 0.06)), "y0": float(rng.uniform(-0.12, 0.12)),
               "yaw0": float(rng.uniform(-np.pi, np.pi))}
    if verb == "lift":
        p["h"] = float(rng.uniform(0.08, 0.22))
    elif verb in ("place", "push"):
        d = float(rng.uniform(0.08, 0.2))
        p.update(d=d, side=side, dy=sign * d, dx=float(rng.uniform(-0.05, 0.05)))
    elif verb == "move":
        p.update(side=side, dy=sign * float(rng.uniform(0.12, 0.22)), bulge=float(rng.uniform(0.05, 0.1)))
    elif verb == "rotate":
        p["angle"] = float(rng.choice([-1, 1]) * rng.uniform(np.radians(45), np.radians(120)))
    elif verb == "pour":
        p.update(side=side, angle=float(rng.uniform(np.radians(60), np.radians(110))))
    elif verb == "flip":
        p["angle"] = float(rng.choice([np.pi / 2, 2 * np.pi / 3, 5 * np.pi / 6]))
    elif verb == "shake":
        p.update(amp=float(rng.uniform(0.02, 0.05)), freq=float(rng.uniform(1.0, 2.0)), n=int(rng.integers(3, 7)))
    elif verb == "reorient":
        p["angle"] = float(rng.choice([-1, 1]) * rng.uniform(np.radians(45), np.radians(110)))
    elif verb == "handover":
        p.update(side=side, dy=sign * float(rng.uniform(0.15, 0.22)))
    return Instruction(verb, object_name, p, _text(verb, object_name, p, 0))


#: Manner phrases appended once a verb's templates are used up, so the 10 paraphrases read differently.
MANNERS = ("", ", slowly", ", carefully", ", in one smooth motion")


def _text(verb: str, object_name: str, p: dict, k: int) -> str:
    """Text of paraphrase ``k``: template ``k mod n``, then a manner phrase for every further round."""
    templates = TEMPLATES[verb]
    fields = {"obj": _category(object_name), "h_cm": round(100 * p.get("h", 0)), "d_cm": round(100 * p.get("d", 0)),
              "deg": round(abs(np.degrees(p.get("angle", 0)))), "side": p.get("side", ""), "n": p.get("n", 0)}
    return templates[k % len(templates)].format(**fields) + MANNERS[(k // len(templates)) % len(MANNERS)]


# ----------------------------------------------------------------------------------------------
# Geometry helpers


def _min_jerk(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10 - 15 * s + 6 * s ** 2)


@functools.lru_cache(maxsize=None)
def _hull_vertices(object_name: str) -> np.ndarray:
    return np.asarray(get_object(object_name).mesh().convex_hull.vertices)


def rest_height(object_name: str, rot: Rotation) -> float:
    """Height of the object's origin above the table when it rests with orientation ``rot``."""
    return float(-rot.apply(_hull_vertices(object_name))[:, 2].min()) + 1e-3


def _pose(pos, rot: Rotation) -> np.ndarray:
    return np.concatenate([np.asarray(pos, float), quat(rot)])


@dataclass
class _Grasp:
    wrist_in_object: np.ndarray   # (7,) wrist pose in the object frame
    angles: np.ndarray            # (20,) closed-hand angles
    preshape: np.ndarray          # (20,) open-hand angles before closing
    approach: np.ndarray          # (3,) world direction the palm moves in to grasp (at grasp time)
    fingers: np.ndarray           # (3,) world direction the fingers point (the grasp axis)
    residual: float               # largest fingertip distance from its target, m
    kind: str


_RELAXED = np.array([0.25, 0.0, 0.3, 0.2] * 4 + [0.3, 0.2, 0.2, 0.2])
_PRESHAPE = np.array([0.1, 0.0, 0.15, 0.1] * 4 + [0.1, 0.5, 0.1, 0.1])


class Synthesizer:
    """Turns instructions into :class:`HumanMotion` (see the module docstring).

    Args:
        noise: what imperfections to add.
        fps: frame rate of the output.
        min_frames: pad the motion (the hand resting after it retreats) to at least this many frames.
    """

    def __init__(self, noise: NoiseConfig = NoiseConfig(), *, fps: float = CONTROL_HZ, min_frames: int = 312):
        self.noise, self.fps, self.min_frames = noise, float(fps), int(min_frames)

    # -- paraphrases ----------------------------------------------------------------------------
    def paraphrases(self, base: Instruction, n: int, seed: int) -> list[Instruction]:
        """``n`` (≤ 10) variants of ``base``: the first is ``base`` itself, the rest change text and motion."""
        if not 1 <= n <= 10:
            raise ConfigError(f"paraphrases per instruction must be in 1..10, got {n}")
        rng = np.random.default_rng([seed, 7])
        out = [base]
        for k in range(1, n):
            style = {"speed": float(rng.uniform(0.75, 1.3)), "curvature": float(rng.uniform(-0.05, 0.05)),
                     "approach_yaw": float(rng.uniform(-0.9, 0.9)), "grasp": int(rng.integers(0, 4)),
                     "timing": float(rng.uniform(0.8, 1.25))}
            out.append(replace(base, text=_text(base.verb, base.object_name, base.params, k), paraphrase=k,
                               style=style))
        return out

    # -- synthesis ------------------------------------------------------------------------------
    def synthesize(self, instr: Instruction, seed: int) -> HumanMotion:
        """The motion of ``instr``; deterministic in ``seed``. Raises ``ValueError`` if no grasp fits."""
        rng = np.random.default_rng([seed, 11])
        nz = self.noise
        info = get_object(instr.object_name)
        p, st = instr.params, instr.style
        hand = HumanHand(scale=0.26 / 0.191 * float(np.exp(rng.normal(0, nz.hand_size))),
                         bone_scale={f: float(np.exp(rng.normal(0, nz.proportion)))
                                     for f in ("index", "middle", "ring", "little", "thumb")})
        # Initial object pose on the table.
        yaw0 = Rotation.from_euler("z", p["yaw0"])
        o0 = _pose([OBJECT_HOME_XY[0] + p["x0"], OBJECT_HOME_XY[1] + p["y0"], info.half_height + REST_GAP], yaw0)
        grasp = self._grasp(instr, o0, hand, rng)
        pieces, kinds = self._object_keyframes(instr, o0, grasp)

        speed = st["speed"]
        dt = 1.0 / self.fps
        dur = {"still": 0.6, "approach": 2.6 * st["timing"], "reach": 1.1, "close": 0.7, "open": 0.7,
               "retreat": 1.6 * st["timing"]}
        dur = {k: v / speed for k, v in dur.items()}
        manip = [(d / speed, pose) for d, pose in pieces]
        t_grasp = dur["still"] + dur["approach"] + dur["reach"]
        t_manip0 = t_grasp + dur["close"]
        t_manip1 = t_manip0 + sum(d for d, _ in manip)
        t_end = t_manip1 + dur["open"] + dur["retreat"]
        n_frames = max(int(np.ceil(t_end * self.fps)) + 12, self.min_frames)
        t = np.arange(n_frames) * dt

        # Object trajectory (what the reference says the object does).
        obj = self._object_path(t, t_manip0, manip, o0, kinds, p, st)
        # The hand follows a copy of the object trajectory shifted by the contact-timing error.
        shift = float(np.clip(rng.normal(0, nz.contact_timing), -0.6, 0.6))
        obj_for_hand = self._object_path(t - shift, t_manip0, manip, o0, kinds, p, st)
        wrist_grasp = compose(obj_for_hand, np.broadcast_to(grasp.wrist_in_object, (n_frames, 7)))
        if instr.verb == "reorient":  # the wrist holds still while the object turns in the hand
            hold = wrist_grasp[np.searchsorted(t, t_manip0 + manip[0][0] - shift)]
            turning = (t - shift >= t_manip0 + manip[0][0]) & (t - shift <= t_manip0 + manip[0][0] + manip[1][0])
            wrist_grasp[turning] = hold
            after = t - shift > t_manip0 + manip[0][0] + manip[1][0]
            wrist_grasp[after] = compose(obj_for_hand[after],
                                         np.broadcast_to(self._regrip(grasp, p["angle"]), (int(after.sum()), 7)))

        wrist = np.empty((n_frames, 7))
        g0 = wrist_grasp[np.searchsorted(t, t_grasp)]
        back = grasp.approach
        pre = _pose(g0[:3] - 0.09 * back + [0, 0, 0.03], rotation(g0[3:]))
        start = self._start_pose(g0, back, o0, st, rng)
        a0, a1 = dur["still"], dur["still"] + dur["approach"]
        phase = np.select([t < a0, t < a1, t < t_grasp],
                          [0, 1, 2], default=3)
        wrist[phase == 0] = start
        m = phase == 1
        wrist[m] = self._curved(start, pre, _min_jerk((t[m] - a0) / (a1 - a0)), st["curvature"])
        m = phase == 2
        wrist[m] = slerp_poses(pre, g0, _min_jerk((t[m] - a1) / (t_grasp - a1)))
        m = phase == 3
        wrist[m] = wrist_grasp[m]
        r0 = t_manip1 + shift + dur["open"]
        release = wrist_grasp[min(np.searchsorted(t, r0), n_frames - 1)]
        retreat_to = _pose(release[:3] - 0.10 * self._approach_now(grasp, release) + [0, 0, 0.12],
                           rotation(release[3:]))
        m = t >= r0
        wrist[m] = slerp_poses(release, retreat_to, _min_jerk((t[m] - r0) / dur["retreat"]))

        # Finger angles: relaxed → pre-shape → closed (the grasp) → open → relaxed.
        closed = grasp.angles
        angles = np.empty((n_frames, NUM_ANGLES))
        keys = [(0.0, _RELAXED), (a0, _RELAXED), (a1, _PRESHAPE), (t_grasp, _PRESHAPE),
                (t_grasp + dur["close"], closed), (t_manip1 + shift, closed),
                (t_manip1 + shift + dur["open"], _PRESHAPE), (t_manip1 + shift + dur["open"] + dur["retreat"], _RELAXED)]
        for (ta, qa), (tb, qb) in zip(keys[:-1], keys[1:]):
            m = (t >= ta) & (t < tb)
            s = _min_jerk((t[m] - ta) / max(tb - ta, 1e-9))[:, None]
            angles[m] = qa + s * (qb - qa)
        angles[t >= keys[-1][0]] = _RELAXED

        # Noise: slow drift of the hand, then per-frame jitter on everything.
        if nz.drift > 0:
            wrist[:, :3] += self._drift(n_frames, nz.drift, rng)
        kp = hand.keypoints(wrist, angles)
        kp = kp + rng.normal(0, nz.jitter, kp.shape) if nz.jitter > 0 else kp
        obj = obj.copy()
        if nz.jitter > 0 or nz.jitter_rot > 0:
            obj[:, :3] += rng.normal(0, nz.jitter, (n_frames, 3))
            obj[:, 3:] = quat(Rotation.from_rotvec(rng.normal(0, nz.jitter_rot, (n_frames, 3))) * rotation(obj[:, 3:]))
        # reach: the hand leaves its pre-grasp pose; placed: the object stops (the hand's release is
        # shifted from it by the contact-timing error)
        phases = {"approach": int(round(a0 * self.fps)), "reach": int(round(a1 * self.fps)),
                  "grasp": int(round(t_grasp * self.fps)), "manipulate": int(round(t_manip0 * self.fps)),
                  "placed": int(round(t_manip1 * self.fps)), "release": int(round((t_manip1 + shift) * self.fps)),
                  "retreat": int(round(r0 * self.fps))}
        meta = {"verb": instr.verb, "params": instr.params, "paraphrase": instr.paraphrase, "style": instr.style,
                "grasp": grasp.kind, "grasp_residual": grasp.residual, "contact_timing_offset": shift,
                "hand_scale": hand.scale, "seed": int(seed), "phases": phases}
        return HumanMotion(instr, kp, obj, wrist, angles, self.fps, phases, meta)

    # -- pieces -----------------------------------------------------------------------------------
    def _object_keyframes(self, instr: Instruction, o0: np.ndarray, grasp: _Grasp):
        """Manipulation as [(duration s, object pose at the end)], plus the kind of each piece."""
        p, name = instr.params, instr.object_name
        r0 = rotation(o0[3:])
        pos0 = o0[:3]
        up = np.array([0.0, 0.0, 1.0])

        def at(dpos, rot=r0, rest=False):
            pos = pos0 + np.asarray(dpos, float)
            pos[0] = np.clip(pos[0], *_X_RANGE)
            pos[1] = np.clip(pos[1], *_Y_RANGE)
            if rest:
                pos[2] = rest_height(name, rot)
            return _pose(pos, rot)

        v = instr.verb
        if v == "lift":
            h = p["h"]
            return [(2.0, at(h * up)), (2.5, at(h * up)), (2.0, at(0 * up, rest=True)), (1.0, at(0 * up, rest=True))], \
                ["move", "hold", "move", "hold"]
        if v in ("place", "handover"):
            lift = 0.08 if v == "place" else 0.16
            d = np.array([p.get("dx", 0.0), p["dy"], 0.0])
            return [(1.5, at(lift * up)), (3.0, at(d + lift * up)), (1.0, at(d + lift * up)),
                    (1.8, at(d, rest=True))], ["move", "transport", "hold", "move"]
        if v == "move":
            d = np.array([0.0, p["dy"], 0.0])
            via = np.array([p["bulge"], p["dy"] / 2, 0.0])
            return [(1.2, at(0.05 * up)), (2.0, at(via + 0.05 * up)), (2.0, at(d + 0.05 * up)),
                    (1.2, at(d, rest=True))], ["move", "transport", "transport", "move"]
        if v == "rotate":
            r1 = Rotation.from_euler("z", p["angle"]) * r0
            return [(1.2, at(0.06 * up)), (3.0, at(0.06 * up, r1)), (1.0, at(0.06 * up, r1)),
                    (1.2, at(0 * up, r1, rest=True))], ["move", "move", "hold", "move"]
        if v == "pour":
            side = 1.0 if p["side"] == "left" else -1.0
            axis = np.array([1.0, 0.0, 0.0]) * side
            r1 = Rotation.from_rotvec(axis * p["angle"]) * r0
            lift = 0.15
            return [(1.8, at(lift * up)), (2.2, at(lift * up, r1)), (1.8, at(lift * up, r1)),
                    (2.2, at(lift * up)), (1.8, at(0 * up, rest=True))], ["move", "move", "hold", "move", "move"]
        if v == "push":
            d = np.array([p.get("dx", 0.0), p["dy"], 0.0])
            return [(4.0, at(d)), (1.0, at(d))], ["transport", "hold"]
        if v == "flip":
            axis = grasp.fingers  # roll over about the grasp axis: the wrist turns, it does not pitch
            r1 = Rotation.from_rotvec(axis * p["angle"]) * r0
            return [(1.8, at(0.14 * up)), (3.0, at(0.14 * up, r1)), (2.0, at(0 * up, r1, rest=True))], \
                ["move", "move", "move"]
        if v == "shake":
            period = 1.0 / p["freq"]
            return [(1.6, at(0.12 * up)), (p["n"] * period, at(0.12 * up)), (1.8, at(0 * up, rest=True))], \
                ["move", "shake", "move"]
        if v == "reorient":
            r1 = self._in_hand_rotation(grasp, p["angle"], o0)
            return [(1.6, at(0.1 * up)), (3.0, at(0.1 * up, r1)), (1.0, at(0.1 * up, r1)),
                    (1.8, at(0 * up, r1, rest=True))], ["move", "move", "hold", "move"]
        raise AssertionError(v)

    def _object_path(self, t, t0, pieces, o0, kinds, p, st) -> np.ndarray:
        out = np.broadcast_to(o0, (len(t), 7)).copy()
        start, ta = o0, t0
        for (d, end), kind in zip(pieces, kinds):
            m = t >= ta
            s = (t[m] - ta) / d
            if kind == "shake":
                seg = np.broadcast_to(start, (int(m.sum()), 7)).copy()
                phase = np.clip(s, 0, 1) * p["n"] * 2 * np.pi
                seg[:, 1] += p["amp"] * np.sin(phase)
            else:
                curv = st["curvature"] if kind == "transport" else 0.0
                seg = self._curved(start, end, _min_jerk(s), curv)
            out[m] = seg
            start, ta = end, ta + d
        return out

    @staticmethod
    def _curved(a: np.ndarray, b: np.ndarray, s: np.ndarray, bulge: float) -> np.ndarray:
        """Poses from ``a`` to ``b`` with a sideways (horizontal) bulge of ``bulge`` m at mid-path."""
        out = slerp_poses(a, b, s)
        if bulge:
            d = b[:3] - a[:3]
            side = np.cross([0.0, 0.0, 1.0], d)
            if np.linalg.norm(side) < 1e-6:
                side = np.array([0.0, 1.0, 0.0])
            out[:, :3] += bulge * np.sin(np.pi * np.clip(s, 0, 1))[:, None] * side / np.linalg.norm(side)
        return out

    @staticmethod
    def _drift(n: int, amp: float, rng) -> np.ndarray:
        """Smooth random offsets (n, 3) with roughly ``amp`` m amplitude (sum of slow sinusoids)."""
        t = np.arange(n)[:, None] / n
        out = np.zeros((n, 3))
        for k in range(1, 4):
            out += rng.normal(0, amp / k, 3) * np.sin(2 * np.pi * (k * t + rng.uniform(0, 1, 3)))
        return out

    def _start_pose(self, g0: np.ndarray, back: np.ndarray, o0: np.ndarray, st: dict, rng) -> np.ndarray:
        """Where the hand starts: about 35 cm from the object, above the table on the robot's side
        (varied by ``approach_yaw``), and at least 30 cm from the robot's base axis."""
        to_base = -o0[:3].copy()
        to_base[2] = 0
        to_base /= np.linalg.norm(to_base)
        yaw = st["approach_yaw"] + rng.normal(0, 0.15)
        d = Rotation.from_euler("z", yaw).apply(to_base)
        pos = o0[:3] + rng.uniform(0.22, 0.28) * d + [0, 0, rng.uniform(0.22, 0.3)]
        dist = np.linalg.norm(pos - o0[:3])
        radial = np.linalg.norm(pos[:2])
        if radial < 0.3:
            pos[:2] *= 0.3 / radial
            # Pushed out from the base axis, the hand can end up nearer the object (as near as 0.19 m
            # for the palm, too close for an episode to start): raise it to keep its distance.
            horizontal = np.linalg.norm(pos[:2] - o0[:2])
            pos[2] = max(pos[2], o0[2] + np.sqrt(max(dist ** 2 - horizontal ** 2, 0.0)))
        # Relaxed start: halfway between palm-down-fingers-forward and the coming grasp's orientation.
        out = np.array([pos[0], pos[1], 0.0]) / np.linalg.norm(pos[:2])
        neutral = Rotation.from_matrix(np.stack([[0.0, 0.0, 1.0], np.cross(out, [0.0, 0.0, 1.0]), out], axis=1))
        half = Slerp([0.0, 1.0], Rotation.concatenate([neutral, rotation(g0[3:])]))(0.5)
        rot = Rotation.from_rotvec(rng.normal(0, 0.15, 3)) * half
        return _pose(pos, rot)

    @staticmethod
    def _approach_now(grasp: _Grasp, wrist: np.ndarray) -> np.ndarray:
        """The palm normal (direction the palm faces) of a wrist pose."""
        return rotation(wrist[3:]).apply([-1.0, 0.0, 0.0])

    # -- grasp --------------------------------------------------------------------------------------
    def _grasp(self, instr: Instruction, o0: np.ndarray, hand: HumanHand, rng) -> _Grasp:
        """Solve a grasp on the resting object: candidates in order of preference, rotated by style."""
        info = get_object(instr.object_name)
        mesh = info.mesh()
        ext = mesh.bounds[1] - mesh.bounds[0]
        to_obj = o0[:3].copy()
        to_obj[2] = 0
        to_obj /= np.linalg.norm(to_obj)
        cands = []
        # End-state comfort: grasp pre-turned against a coming rotation, so the wrist turns through neutral.
        pre_turn = -0.5 * instr.params["angle"] if instr.verb == "rotate" else 0.0
        for k in range(8):
            yaw = ((k + 1) // 2) * np.pi / 6 * (1 if k % 2 == 0 else -1) + instr.style["approach_yaw"] * 0.3 + pre_turn
            fingers = Rotation.from_euler("z", yaw).apply(to_obj)     # fingers point away from the robot
            top = bool((k % 4) != 3 or ext[2] < 0.05 or instr.verb == "push")
            cands.append((top, fingers))
        start = instr.style["grasp"] % len(cands)
        cands = cands[start:] + cands[:start]
        if instr.verb == "push":  # the hand holds the object from above and slides it
            cands = [c for c in cands if c[0] is True]
        best = None
        for top, fingers in cands:
            g = self._solve_grasp(mesh, o0, hand, top, fingers, rng)
            if g is not None and (best is None or g.residual < best.residual):
                best = g
            if best is not None and best.residual < 0.012:
                break
        if best is None:
            raise ConfigError(f"no grasp fits {instr.object_name!r} for {instr.text!r}")
        return best

    def _solve_grasp(self, mesh, o0, hand: HumanHand, top, fingers: np.ndarray, rng):
        """Grasp from above (``top`` True), from the side (False), or palm facing the direction ``top``."""
        r_obj = rotation(o0[3:])
        world_mesh_v = r_obj.apply(np.asarray(mesh.vertices)) + o0[:3]
        center = o0[:3].copy()
        zmin, zmax = world_mesh_v[:, 2].min(), world_mesh_v[:, 2].max()
        if isinstance(top, np.ndarray):
            approach, top = top / np.linalg.norm(top), False
        else:
            approach = np.array([0.0, 0.0, -1.0]) if top else np.cross(fingers, [0.0, 0.0, 1.0])
            if not top and np.dot(approach, center) < 0:
                approach = -approach
        center[2] = zmin + (0.65 if top else 0.5) * (zmax - zmin)
        g = fingers / np.linalg.norm(fingers)
        spread_axis = np.cross(g, -approach)
        spacing = 0.02 * hand.scale
        origins, dirs = [], []
        for off in (0.0, spacing, 0.0, -spacing):           # thumb, index, middle, ring
            origins.append(center + off * spread_axis)
        origins = np.array(origins)
        dirs = np.array([g] + [-g] * 3)
        starts = origins - 0.4 * dirs
        # Ray cast in the object frame.
        o_loc = r_obj.inv().apply(starts - o0[:3])
        d_loc = r_obj.inv().apply(dirs)
        dist, tri = first_hits(mesh.triangles, o_loc, d_loc)
        if not np.isfinite(dist[:3:2]).all():   # thumb and middle finger must touch
            return None
        for k, off in ((1, spacing), (3, -spacing)):  # a small object: that finger rests beside the middle one
            if not np.isfinite(dist[k]):
                dist[k], tri[k] = dist[2], tri[2]
                o_loc[k] = o_loc[2]
        contact = r_obj.apply(o_loc + dist[:, None] * d_loc) + o0[:3]
        normal = r_obj.apply(mesh.face_normals[tri])
        for k, off in ((1, spacing), (3, -spacing)):
            if np.allclose(o_loc[k], o_loc[2]):
                contact[k] = contact[2] + off * spread_axis
        width = np.dot(contact[1] - contact[0], g)
        if not 0.005 < width < 0.11 * hand.scale:
            return None
        pad = 0.008 * hand.scale
        pen = rng.uniform(0, self.noise.penetration, 4)
        targets = contact + normal * (pad - pen)[:, None]
        x_axis = -approach
        rot = Rotation.from_matrix(np.stack([x_axis, np.cross(g, x_axis), g], axis=1))
        tips = [TIP_INDEX[f] for f in ("thumb", "index", "middle", "ring")]
        little = TIP_INDEX["little"]
        mid = np.array([0.6, 0.0, 0.7, 0.5] * 4 + [0.5, 0.4, 0.4, 0.4])
        lo, hi = ANGLE_LIMITS[:, 0], ANGLE_LIMITS[:, 1]
        x0 = np.concatenate([center - 0.16 * hand.scale * g - 0.06 * approach, mid])
        q = quat(rot)

        def keypoints(xs: np.ndarray) -> np.ndarray:
            poses = np.concatenate([xs[:, :3], np.broadcast_to(q, (len(xs), 4))], axis=1)
            return hand.keypoints(poses, xs[:, 3:])

        def residual_many(xs):
            kp = keypoints(xs)
            r = [(kp[:, tips] - targets).reshape(len(xs), -1),
                 0.3 * (kp[:, little] - (targets[3] - spacing * spread_axis)),
                 0.02 * (xs[:, 3:] - mid),
                 3.0 * np.maximum(0.0, (kp[:, 0] - center) @ approach + 0.03)[:, None]]
            return np.concatenate(r, axis=1)

        def fun(x):
            return residual_many(x[None])[0]

        def jac(x):
            eps = 1e-6
            xs = np.vstack([x, x + eps * np.eye(len(x))])
            r = residual_many(xs)
            return ((r[1:] - r[0]) / eps).T

        bounds = (np.concatenate([np.full(3, -np.inf), lo]), np.concatenate([np.full(3, np.inf), hi]))
        sol = least_squares(fun, np.clip(x0, *bounds), jac=jac, bounds=bounds, max_nfev=60)
        kp = keypoints(sol.x[None])[0]
        residual = float(np.linalg.norm(kp[tips] - targets, axis=1).max())
        wrist_world = _pose(sol.x[:3], rot)
        return _Grasp(wrist_in_object=compose(inverse(o0), wrist_world), angles=sol.x[3:], preshape=_PRESHAPE,
                      approach=approach, fingers=g, residual=residual, kind="top" if top else "side")

    @staticmethod
    def _in_hand_rotation(grasp: _Grasp, angle: float, o0: np.ndarray) -> Rotation:
        """Object orientation after turning ``angle`` about the grasp axis (fingers' direction)."""
        axis = rotation(compose(o0, grasp.wrist_in_object)[3:]).apply([0.0, 0.0, 1.0])
        return Rotation.from_rotvec(axis * angle) * rotation(o0[3:])

    @staticmethod
    def _regrip(grasp: _Grasp, angle: float) -> np.ndarray:
        """Wrist pose in the object frame after the object turned ``angle`` about the grasp axis."""
        w = grasp.wrist_in_object
        axis_obj = rotation(w[3:]).apply([0.0, 0.0, 1.0])
        turn = _pose([0, 0, 0], Rotation.from_rotvec(-axis_obj * angle))
        return compose(turn, w)
