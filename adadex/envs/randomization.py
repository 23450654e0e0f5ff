"""Domain randomization (paper Table 3), drawn per world at each reset.

Physics: robot link masses, friction, servo stiffness (kp) and damping (joint damping and the
servos' kv) scaled by U[0.9, 1.1]; object mass and friction scaled by U[0.7, 1.3]; restitution
+U[0, 0.4] (MuJoCo contacts are not bouncy by default; a restitution e is obtained with the contact
damping ratio −ln e / √(π² + ln² e)); object size scaled by U[0.95, 1.05], quantized to
``object_scale_levels`` values so each (object, size) scene compiles once. Initial object pose:
x, y + N(0, 0.05) m, yaw + N(0, 0.5) rad. Observation noise N(0, 0.002) on the joint positions
and the tracked-link positions; action noise: a per-episode offset N(0, 0.02) (correlated) plus
a per-step N(0, 0.05) (uncorrelated), in rad of joint-target change.

Every range is a config value; :meth:`Randomization.off` turns everything off.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, fields

import mujoco
import numpy as np

from adadex.errors import check_number
from adadex.sim.scene import OBJECT_BODY


@dataclass(frozen=True)
class Randomization:
    """Ranges of the per-world randomization (see the module docstring)."""

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

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, tuple):
                lo, hi = v
                if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
                    raise ValueError(f"Randomization.{f.name} must be a range 0 ≤ low ≤ high, got {v}")
                if f.name == "object_restitution" and hi >= 1:
                    raise ValueError(f"Randomization.object_restitution must stay below 1, got {v}")
            else:
                check_number(f"Randomization.{f.name}", v)
        if self.object_scale_levels < 1:
            raise ValueError(f"object_scale_levels must be ≥ 1, got {self.object_scale_levels}")

    @classmethod
    def off(cls) -> Randomization:
        one = (1.0, 1.0)
        return cls(robot_mass=one, robot_friction=one, robot_stiffness=one, robot_damping=one, object_mass=one,
                   object_friction=one, object_restitution=(0.0, 0.0), object_scale=one, object_scale_levels=1,
                   object_xy_std=0.0, object_yaw_std=0.0, proprio_noise=0.0, action_noise_correlated=0.0,
                   action_noise_uncorrelated=0.0)

    def as_dict(self) -> dict:
        return asdict(self)

    def scale_levels(self) -> np.ndarray:
        lo, hi = self.object_scale
        return np.linspace(lo, hi, self.object_scale_levels) if self.object_scale_levels > 1 else np.array([0.5 * (lo + hi)])


class ModelRandomizer:
    """Writes one world's randomized physics into a copy of its scene model."""

    def __init__(self, model: mujoco.MjModel):
        base = model.body("link_base").id
        obj = model.body(OBJECT_BODY).id
        root = model.body_rootid
        self.robot_bodies = np.flatnonzero((root == base) & (np.arange(model.nbody) != 0))
        self.object_body = obj
        self.robot_geoms = np.flatnonzero(np.isin(model.geom_bodyid, self.robot_bodies))
        self.object_geoms = np.flatnonzero((model.geom_bodyid == obj) & (model.geom_contype > 0))
        self.robot_dofs = np.flatnonzero(np.isin(model.dof_bodyid, self.robot_bodies))

    def apply(self, model: mujoco.MjModel, cfg: Randomization, rng: np.random.Generator) -> mujoco.MjModel:
        """A randomized copy of ``model`` (which is left untouched)."""
        m = copy.copy(model)

        def u(r):
            return rng.uniform(*r)

        s = u(cfg.robot_mass)
        m.body_mass[self.robot_bodies] *= s
        m.body_inertia[self.robot_bodies] *= s
        m.geom_friction[self.robot_geoms, 0] *= u(cfg.robot_friction)
        k = u(cfg.robot_stiffness)
        m.actuator_gainprm[:, 0] *= k
        m.actuator_biasprm[:, 1] *= k
        d = u(cfg.robot_damping)
        m.dof_damping[self.robot_dofs] *= d
        m.actuator_biasprm[:, 2] *= d
        s = u(cfg.object_mass)
        m.body_mass[self.object_body] *= s
        m.body_inertia[self.object_body] *= s
        m.geom_friction[self.object_geoms, 0] *= u(cfg.object_friction)
        e = u(cfg.object_restitution)
        if e > 0:
            m.geom_solref[self.object_geoms, 1] = -math.log(e) / math.sqrt(math.pi ** 2 + math.log(e) ** 2)
        return m
