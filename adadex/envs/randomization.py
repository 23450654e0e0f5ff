"""Domain randomization (paper Table 3), drawn per world at each reset.

Robot physics is a distribution over *effect parameters* (:mod:`adadex.sim.effects`): each reset
samples a :class:`~adadex.sim.patch.ModelPatch` per world and applies it with the effects' own code
to a copy of the world's compiled scene (no recompilation). The Table 3 defaults: link masses
(``mass_scale``), friction (``friction_scale``), servo stiffness (``kp_scale``) and damping
(``damping_scale``: joint damping and the servos' kv) scaled by U[0.9, 1.1] — one draw per world
for all 22 joints. Further ranges (:class:`EffectRange`) randomize any model-stage effect per
joint; :meth:`Randomization.from_patch` builds them around a fitted patch's 95 % intervals (the
paper sets its randomization from system identification).

A patch and randomization compose (:meth:`Randomization.world_patch`): the draws randomize *around
the patched robot*. A range's draw acts on top of the env's patch as the effect's parameters say
(:meth:`~adadex.sim.patch.ModelPatch.composed`): scale effects multiply (a patch's ``kp_scale`` 0.3
under a Table 3 draw of 1.05 gives 0.315, an arm_j1 gain of 1500 · 0.315), offset effects add (a
patch's ``damping`` plus a drawn ``damping``), each result clipped to the effect's bounds. Ranges
marked ``absolute`` — those :meth:`Randomization.from_patch` builds — draw the value itself (the
fit's interval is of the value): their draw replaces the patch's value on that effect and joint, so
a patch that also carries the fit (``TrackingEnv(patch=fit, randomize=Randomization.from_patch(fit))``)
is not applied twice. Structure-, command- and sensor-stage effects (delays, lags, backlash, encoder
offsets) are not drawn per world: they act at the patch's values in every world.

The object: mass and friction scaled by U[0.7, 1.3]; restitution +U[0, 0.4] (MuJoCo contacts are
not bouncy by default; a restitution e is obtained with the contact damping ratio
−ln e / √(π² + ln² e)); size scaled by U[0.95, 1.05], quantized to ``object_scale_levels`` values
so each (object, size) scene compiles once. Initial object pose: x, y + N(0, 0.05) m,
yaw + N(0, 0.5) rad. Observation noise N(0, 0.002) on the joint positions and the tracked-link
positions; action noise: a per-episode offset N(0, 0.02) (correlated) plus a per-step N(0, 0.05)
(uncorrelated), **in units of the action bound** (``TrackingConfig.max_action``: 0.005 rad per step
at 0.1 rad), added before the action is clipped to that bound. The paper trains in Isaac Gym, and
Table 3's observation and per-step action noise are the numbers of IsaacGymEnvs' dexterous-hand
randomization configs, whose ``VecTask.step`` adds the action noise to the policy's normalized
action (in [−1, 1]) before clipping and scaling it. Read in radians instead, N(0, 0.05) per step
shakes the palm by about 2.5 cm at 12 Hz and kinematic replay loses the grasp of a mug it otherwise
lifts (docs/training-log.md).

Every range is a config value; :meth:`Randomization.off` turns everything off.

Example
-------
>>> import numpy as np
>>> rnd = Randomization()
>>> patch = rnd.sample_patch(np.random.default_rng(0))
>>> sorted(e.effect for e in patch.effects)
['damping_scale', 'friction_scale', 'kp_scale', 'mass_scale']
>>> bool(np.all(np.abs(patch.effects[0].values - 1) <= 0.1))
True
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, field, fields

import mujoco
import numpy as np

from adadex.errors import ConfigError, ConfigTypeError, check_number
from adadex.sim.effects import EffectError, get_effect, set_const
from adadex.sim.patch import EffectInstance, ModelPatch
from adadex.sim.robot import JOINT_NAMES
from adadex.sim.scene import OBJECT_BODY

#: Randomization field → the effect its range scales on every robot joint.
TABLE3_EFFECTS = {"robot_mass": "mass_scale", "robot_friction": "friction_scale",
                  "robot_stiffness": "kp_scale", "robot_damping": "damping_scale"}


@dataclass(frozen=True, eq=False)
class EffectRange:
    """Uniform range of one model-stage effect's parameters on some joints.

    ``low``/``high`` broadcast to (len(joints), n_params) and lie inside the effect's bounds.
    ``shared``: one uniform draw per world moves every joint's value alike (Table 3's global
    scales); otherwise each joint and parameter is drawn independently.

    ``absolute``: how a draw meets the env's patch on the same effect and joint. ``False`` (the
    default, Table 3): the draw acts on top of the patched value — a scale multiplies it, an
    offset adds to it (:meth:`~adadex.sim.patch.ModelPatch.composed`). ``True``
    (:meth:`Randomization.from_patch`): the draw *is* the value and replaces the patch's.

    Attributes:
        effect: the effect's name (a model-stage effect of :mod:`adadex.sim.effects`; others raise
            :class:`~adadex.sim.effects.EffectError`).
        joints: the joints it is drawn on.
        low: lower end of the range, broadcast to (len(joints), n_params), in the effect's units.
        high: upper end, likewise; not below ``low``.
        shared: one draw per world for every joint (default False: each joint and parameter
            independently).
        absolute: the draw replaces the patch's value (default False: it composes with it).
    """

    effect: str
    joints: tuple[str, ...]
    low: np.ndarray
    high: np.ndarray
    shared: bool = False
    absolute: bool = False

    def __post_init__(self):
        eff = get_effect(self.effect)
        if eff.stage != "model":
            raise EffectError(f"{eff.name}: only model-stage effects can be drawn per world (every world "
                              f"shares one compiled structure); put {eff.stage}-stage effects in the patch")
        object.__setattr__(self, "joints", tuple(self.joints))
        lo, hi = eff.validate(self.joints, self.low), eff.validate(self.joints, self.high)
        if (lo > hi).any():
            raise EffectError(f"{eff.name}: range low {lo.tolist()} above high {hi.tolist()}")
        object.__setattr__(self, "low", lo)
        object.__setattr__(self, "high", hi)

    def is_constant_absent(self) -> bool:
        eff = get_effect(self.effect)
        return bool(np.array_equal(self.low, self.high) and eff.is_absent(self.low))

    def without(self, joints) -> EffectRange | None:
        keep = [i for i, j in enumerate(self.joints) if j not in set(joints)]
        if not keep:
            return None
        return EffectRange(self.effect, tuple(self.joints[i] for i in keep), self.low[keep], self.high[keep],
                           self.shared, self.absolute)

    def sample(self, rng: np.random.Generator) -> EffectInstance:
        u = rng.uniform() if self.shared else rng.uniform(size=self.low.shape)
        return EffectInstance(self.effect, self.joints, np.clip(self.low + u * (self.high - self.low),
                                                                self.low, self.high))


@dataclass(frozen=True)
class Randomization:
    """Ranges of the per-world randomization (see the module docstring).

    ``effects`` are further per-joint ranges; on an (effect, joint) they replace the Table 3
    range. ``patch`` holds effects every world carries (:meth:`from_patch` puts the fit there);
    :class:`~adadex.envs.tracking.TrackingEnv` puts its own patch over it (the env's entries replace
    its entries on the same effect and joint), and each world's draw then composes with the result
    (:meth:`world_patch`: relative ranges on top of the patched values, absolute ones replacing them).

    Ranges are (low, high) of a uniform draw; the defaults are Table 3's. Scales are factors on the
    nominal value (1: unchanged).

    Attributes:
        robot_mass: scale of every robot link's mass, U[low, high], one draw per world
            (``mass_scale``; default (0.9, 1.1)).
        robot_friction: scale of the robot's friction (``friction_scale``; default (0.9, 1.1)).
        robot_stiffness: scale of the servos' stiffness kp (``kp_scale``; default (0.9, 1.1)).
        robot_damping: scale of joint damping and the servos' kv (``damping_scale``; default (0.9, 1.1)).
        object_mass: scale of the object's mass (default (0.7, 1.3)).
        object_friction: scale of the object's friction (default (0.7, 1.3)).
        object_restitution: restitution added to the object's contacts, U[low, high], below 1
            (default (0, 0.4)).
        object_scale: scale of the object's size, quantized to ``object_scale_levels`` values
            (default (0.95, 1.05)).
        object_scale_levels: how many sizes ``object_scale`` is quantized to, each compiled once
            (default 5).
        object_xy_std: std of the object's initial x, y offset, m (default 0.05).
        object_yaw_std: std of the object's initial yaw offset, rad (default 0.5).
        proprio_noise: std of the noise on the observed joint positions (rad) and link positions (m)
            (default 0.002).
        action_noise_correlated: std of a per-episode action offset, in units of the action bound
            (``TrackingConfig.max_action``; default 0.02).
        action_noise_uncorrelated: std of the per-step action noise, in units of the action bound
            (default 0.05).
        effects: further per-joint ranges (:class:`EffectRange`); on an (effect, joint) they replace
            the Table 3 range (default none).
        patch: effects every world carries (:meth:`from_patch` puts a fit there); ``None`` (default):
            none.

    Example:
        >>> Randomization.off().object_xy_std
        0.0
    """

    robot_mass: tuple[float, float] = (0.9, 1.1)
    robot_friction: tuple[float, float] = (0.9, 1.1)
    robot_stiffness: tuple[float, float] = (0.9, 1.1)
    robot_damping: tuple[float, float] = (0.9, 1.1)
    object_mass: tuple[float, float] = (0.7, 1.3)
    object_friction: tuple[float, float] = (0.7, 1.3)
    object_restitution: tuple[float, float] = (0.0, 0.4)
    object_scale: tuple[float, float] = (0.95, 1.05)
    object_scale_levels: int = 5
    object_xy_std: float = 0.05
    object_yaw_std: float = 0.5
    proprio_noise: float = 0.002
    action_noise_correlated: float = 0.02
    action_noise_uncorrelated: float = 0.05
    effects: tuple[EffectRange, ...] = ()
    patch: ModelPatch | None = field(default=None, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "effects", tuple(self.effects))
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("effects", "patch"):
                continue
            if isinstance(v, tuple):
                lo, hi = v
                if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
                    raise ConfigError(f"Randomization.{f.name} must be a range 0 ≤ low ≤ high, got {v}")
                if f.name == "object_restitution" and hi >= 1:
                    raise ConfigError(f"Randomization.{f.name} must stay below 1, got {v}")
            else:
                check_number(f"Randomization.{f.name}", v)
        if self.object_scale_levels < 1:
            raise ConfigError(f"object_scale_levels must be ≥ 1, got {self.object_scale_levels}")
        if not all(isinstance(r, EffectRange) for r in self.effects):
            raise ConfigTypeError("Randomization.effects must be EffectRange objects")
        self.effect_ranges()           # the Table 3 ranges must lie inside their effects' bounds

    @classmethod
    def off(cls) -> Randomization:
        one = (1.0, 1.0)
        return cls(robot_mass=one, robot_friction=one, robot_stiffness=one, robot_damping=one, object_mass=one,
                   object_friction=one, object_restitution=(0.0, 0.0), object_scale=one, object_scale_levels=1,
                   object_xy_std=0.0, object_yaw_std=0.0, proprio_noise=0.0, action_noise_correlated=0.0,
                   action_noise_uncorrelated=0.0)

    @classmethod
    def from_patch(cls, patch, *, widen: float = 1.0, fraction: float = 0.1,
                   base: Randomization | None = None) -> Randomization:
        """Randomization around a fitted patch (a :class:`ModelPatch` or its file).

        Each model-stage effect of the patch is drawn per world and joint from its fit's 95 %
        interval (``ci95`` in the patch) widened ``widen``-fold about the fitted value; where the
        patch has no interval, from value ± ``fraction`` · |value|; clipped to the effect's bounds.
        These ranges are ``absolute``: a draw is the effect's value on that joint and replaces the
        value of the env's patch there (which, from ``patch``, is the fitted value itself — it is
        not applied a second time on top of the draw). Every other setting comes from ``base``
        (default: Table 3, whose robot scales still apply to the effects and joints the patch
        does not name, composing with the patch's values as :meth:`world_patch` says). The patch's
        other effects (structure, command and sensor stages: delays, lags, backlash, encoder
        offsets) act at their fitted values in every world, through ``patch``.
        """
        patch = patch if isinstance(patch, ModelPatch) else ModelPatch.load(patch)
        check_number("Randomization.from_patch widen", widen)
        check_number("Randomization.from_patch fraction", fraction)
        base = base if base is not None else cls()
        ranges = []
        for e in patch.active().stage("model").effects:
            v = e.values
            if e.ci95 is not None:
                lo, hi = v - widen * (v - e.ci95[..., 0]), v + widen * (e.ci95[..., 1] - v)
            else:
                lo, hi = v - fraction * np.abs(v), v + fraction * np.abs(v)
            blo, bhi = get_effect(e.effect).bounds(e.joints)
            ranges.append(EffectRange(e.effect, e.joints, np.clip(lo, blo, bhi), np.clip(hi, blo, bhi),
                                      absolute=True))
        kept = base.patch.updated(patch) if base.patch is not None else patch
        return cls(**{f.name: getattr(base, f.name) for f in fields(base) if f.name not in ("effects", "patch")},
                   effects=base.effects + tuple(ranges), patch=kept)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["effects"] = [{"effect": r.effect, "joints": list(r.joints), "low": r.low.tolist(), "high": r.high.tolist(),
                         "shared": r.shared, "absolute": r.absolute} for r in self.effects]
        d["patch"] = None if self.patch is None else self.patch.to_dict()
        return d

    def scale_levels(self) -> np.ndarray:
        lo, hi = self.object_scale
        if self.object_scale_levels == 1:
            return np.array([0.5 * (lo + hi)])
        return np.linspace(lo, hi, self.object_scale_levels)

    def effect_ranges(self) -> tuple[EffectRange, ...]:
        """The robot-physics ranges drawn per world: Table 3's, then ``effects`` (a later range
        replaces an earlier one on the same effect and joint); ranges fixed at "absent" left out."""
        table = [EffectRange(eff, JOINT_NAMES, getattr(self, name)[0], getattr(self, name)[1], shared=True)
                 for name, eff in TABLE3_EFFECTS.items()]
        out: list[EffectRange] = []
        for r in table + list(self.effects):
            out = [k for k in (o.without(r.joints) if o.effect == r.effect else o for o in out) if k is not None]
            out.append(r)
        return tuple(r for r in out if not r.is_constant_absent())

    def sample_patch(self, rng: np.random.Generator, ranges: tuple[EffectRange, ...] | None = None) -> ModelPatch:
        """One world's raw draw of the robot-physics effects (``ranges``: :meth:`effect_ranges`,
        precomputed), before it meets a patch (:meth:`world_patch`)."""
        ranges = self.effect_ranges() if ranges is None else ranges
        return ModelPatch(tuple(r.sample(rng) for r in ranges))

    def world_patch(self, patch: ModelPatch, rng: np.random.Generator,
                    ranges: tuple[EffectRange, ...] | None = None) -> ModelPatch:
        """One world's robot: ``patch`` with a draw of the ranges around it (the same draws, from
        the same ``rng`` state, as :meth:`sample_patch`). A relative range's draw composes with the
        patch's value on its effect and joint (:meth:`ModelPatch.composed`: scales multiply,
        offsets add, clipped to the bounds); an absolute range's draw (:meth:`from_patch`) replaces it."""
        ranges = self.effect_ranges() if ranges is None else ranges
        draws = [(r.absolute, r.sample(rng)) for r in ranges]
        relative = ModelPatch(tuple(d for absolute, d in draws if not absolute))
        absolute = ModelPatch(tuple(d for absolute, d in draws if absolute))
        return patch.composed(relative).updated(absolute)


class ModelRandomizer:
    """Writes one world's randomized object physics into a copy of its scene model (the robot's
    physics is an effect patch, applied by the caller with the effects' code).

    Args:
        model: a scene model holding the object (its body :data:`~adadex.sim.scene.OBJECT_BODY`);
            the object's body and its colliding geoms are looked up once, for :meth:`apply`.
    """

    def __init__(self, model: mujoco.MjModel):
        obj = model.body(OBJECT_BODY).id
        self.object_body = obj
        self.object_geoms = np.flatnonzero((model.geom_bodyid == obj) & (model.geom_contype > 0))

    def apply(self, model: mujoco.MjModel, cfg: Randomization, rng: np.random.Generator) -> mujoco.MjModel:
        """A copy of ``model`` (which is left untouched) with the object's physics randomized."""
        m = copy.copy(model)

        def u(r):
            return rng.uniform(*r)

        s = u(cfg.object_mass)
        m.body_mass[self.object_body] *= s
        m.body_inertia[self.object_body] *= s
        if s != 1.0:
            set_const(m)
        m.geom_friction[self.object_geoms, 0] *= u(cfg.object_friction)
        e = u(cfg.object_restitution)
        if e > 0:
            m.geom_solref[self.object_geoms, 1] = -math.log(e) / math.sqrt(math.pi ** 2 + math.log(e) ** 2)
        return m
