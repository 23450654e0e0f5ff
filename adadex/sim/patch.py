"""Model patches: a list of physical effects with joints and parameter values, saved as JSON.

A patch is what the sysid workbench writes after fitting and what a TrackingEnv, the recording
simulator and the workbench itself load, so that every part of adadex runs the same corrected
simulator. File format (``version`` 1)::

    {"version": 1, "model": "builtin",
     "effects": [{"effect": "coulomb_friction", "joints": ["if_pip", "if_dip"],
                  "params": {"friction": [0.05, 0.04]},
                  "ci95": {"friction": [[0.046, 0.054], [0.037, 0.043]]}}]}

``ci95`` is optional: a fit's 95 % confidence interval per parameter and joint, in the layout the
workbench's diagnosis uses; :meth:`adadex.envs.randomization.Randomization.from_patch` builds
domain-randomization ranges from it.

:func:`patched_scene` is the one place a scene is compiled with a patch (structural edits before
compiling, parameters after); it caches the compiled models on the patch's content.

``model`` is the :attr:`~adadex.sim.model_source.ModelSource.model_id` the patch was fitted on
(``"builtin"``, or a user's MJCF file name with its content hash); a patch of one model is refused
on another (:class:`PatchError`). Files without ``model`` are patches of the built-in robot. A
patch made on a user's model carries that model's :class:`~adadex.sim.model_source.RobotTable`
(``robot``): joint names and bounds are checked against it.

Example
-------
>>> from adadex.sim.patch import ModelPatch
>>> patch = ModelPatch.from_dict({"effects": [
...     {"effect": "damping", "joints": ["if_pip"], "params": {"damping": [0.2]}}]})
>>> model = patch.build_model()
>>> round(float(model.dof_damping[8]), 3)
0.23
"""

from __future__ import annotations

import copy
import functools
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from adadex.errors import AdadexError
from adadex.io import atomic_write_text
from adadex.sim.effects import EffectError, ModelBase, get_effect
from adadex.sim.model_source import BUILTIN_ID, same_model
from adadex.sim.robot import joint_index
from adadex.sim.scene import PhysicsOptions, build_scene_spec

PATCH_VERSION = 1


class PatchError(AdadexError, ValueError):
    """A malformed model patch; the message names the file and the entry."""


@dataclass(frozen=True)
class EffectInstance:
    """One effect on some joints with values of shape (len(joints), n_params), and optionally a
    fit's 95 % intervals ``ci95`` of shape (len(joints), n_params, 2) (``None``: not known)."""

    effect: str
    joints: tuple[str, ...]
    values: np.ndarray
    ci95: np.ndarray | None = field(default=None, compare=False)
    #: The user model's joint table the joints and bounds refer to (None: the built-in robot).
    robot: object = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        eff = get_effect(self.effect)
        object.__setattr__(self, "joints", tuple(self.joints))
        object.__setattr__(self, "values", eff.validate(self.joints, self.values, self.robot))
        if self.ci95 is not None:
            ci = np.asarray(self.ci95, dtype=float)
            shape = (len(self.joints), len(eff.params), 2)
            if ci.ndim == 3 and ci.shape[0] == shape[0] and ci.shape[2] == 2 and 1 <= ci.shape[1] < shape[1]:
                # intervals of the leading parameters only: the others are at their absent values (as values)
                rest = np.repeat(eff.absent_values()[ci.shape[1]:, None], 2, axis=1)
                ci = np.concatenate([ci, np.broadcast_to(rest, (shape[0], *rest.shape))], axis=1)
            if ci.shape != shape or not np.isfinite(ci).all() or (ci[..., 0] > ci[..., 1]).any():
                raise PatchError(f"{eff.name}: ci95 must be finite [low, high] pairs of shape {shape}, "
                                 f"got {ci.tolist()}")
            object.__setattr__(self, "ci95", ci)

    @property
    def spec(self):
        return get_effect(self.effect)

    @property
    def jid(self) -> np.ndarray:
        jid = self.__dict__.get("_jid")        # computed once: a reset applies a patch per world
        if jid is None:
            jid = joint_index(self.joints) if self.robot is None else self.robot.index(self.joints)
            object.__setattr__(self, "_jid", jid)
        return jid

    def is_absent(self) -> bool:
        return self.spec.is_absent(self.values)

    def to_dict(self) -> dict:
        d = {"effect": self.effect, "joints": list(self.joints),
             "params": {p: [float(v) for v in self.values[:, i]] for i, p in enumerate(self.spec.param_names)}}
        if self.ci95 is not None:
            d["ci95"] = {p: [[float(a), float(b)] for a, b in self.ci95[:, i]]
                         for i, p in enumerate(self.spec.param_names)}
        return d

    def without(self, joints) -> "EffectInstance | None":
        """This effect on its other joints (``None`` when none is left)."""
        keep = [i for i, j in enumerate(self.joints) if j not in set(joints)]
        if not keep:
            return None
        return EffectInstance(self.effect, tuple(self.joints[i] for i in keep), self.values[keep],
                              None if self.ci95 is None else self.ci95[keep], self.robot)

    @classmethod
    def from_dict(cls, d: dict, robot=None) -> "EffectInstance":
        if not isinstance(d, dict) or "effect" not in d or "joints" not in d:
            raise PatchError(f"an effect entry needs 'effect' and 'joints', got {d!r}")
        eff = get_effect(d["effect"])
        joints = d["joints"]
        if not isinstance(joints, (list, tuple)) or not joints or not all(isinstance(j, str) for j in joints):
            # a string would be read letter by letter
            raise PatchError(f"{eff.name}: 'joints' must be a non-empty list of joint names such as [\"if_pip\"], "
                             f"got {json.dumps(joints, default=str)}")
        params = d.get("params", {})
        if not isinstance(params, dict):
            raise PatchError(f"{eff.name}: 'params' must be an object of parameter values, got {params!r}")
        unknown = set(params) - set(eff.param_names)
        if unknown:
            raise PatchError(f"{eff.name}: unknown parameters {sorted(unknown)}; it takes {list(eff.param_names)}")
        cols = []
        for p, absent in zip(eff.param_names, eff.absent_values()):
            v = np.asarray(params.get(p, absent), dtype=float)
            cols.append(np.broadcast_to(v, (len(joints),)) if v.ndim == 0 else v)
        try:
            values = np.stack(cols, axis=1)
        except ValueError as e:
            raise PatchError(f"{eff.name}: one value per joint expected for {joints}: {e}") from None
        ci = d.get("ci95")
        if ci is not None:
            # a parameter the file does not name is at its absent value (a patch written before the effect
            # gained it: payload_mass's offset), its interval that value
            if not isinstance(ci, dict) or not set(params) <= set(ci) <= set(eff.param_names):
                raise PatchError(f"{eff.name}: ci95 must give intervals for {list(eff.param_names)}, got {ci!r}")
            try:
                ci = np.stack([np.asarray(ci[p], dtype=float).reshape(len(joints), 2) if p in ci
                               else np.full((len(joints), 2), a) for p, a in zip(eff.param_names, eff.absent_values())],
                              axis=1)
            except ValueError as e:
                raise PatchError(f"{eff.name}: ci95 needs one [low, high] per joint for {joints}: {e}") from None
        return cls(eff.name, tuple(joints), values, ci, robot)


@dataclass(frozen=True)
class ModelPatch:
    """An ordered set of effects; the same (effect, joint) pair may appear only once.

    Attributes:
        effects: the effects (:class:`EffectInstance`), applied in order. Each is rebound to the
            patch's ``robot``; an (effect, joint) pair given twice raises :class:`PatchError`.
        robot: the joint table of the user model the patch belongs to (None: the model of the
            effects — a user model's effects carry its table — else the built-in robot). Effects
            of two different models raise :class:`PatchError`. Not part of equality.

    Examples:
        >>> len(ModelPatch())
        0
        >>> ModelPatch().model_id == BUILTIN_ID
        True
    """

    effects: tuple[EffectInstance, ...] = ()
    robot: object = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        if self.robot is None:   # effects of a user's model keep their model: identity travels with them
            owners = {e.robot.model_id: e.robot for e in self.effects if e.robot is not None}
            if len(owners) > 1:
                raise PatchError(f"the effects belong to different models: {', '.join(sorted(owners))}")
            object.__setattr__(self, "robot", next(iter(owners.values()), None))
        if self.robot is not None and self.robot.builtin:
            object.__setattr__(self, "robot", None)
        object.__setattr__(self, "effects", tuple(
            e if e.robot is self.robot else EffectInstance(e.effect, e.joints, e.values, e.ci95, self.robot)
            for e in self.effects))
        seen = set()
        for e in self.effects:
            for j in e.joints:
                if (e.effect, j) in seen:
                    raise PatchError(f"effect {e.effect} is given twice for joint {j}")
                seen.add((e.effect, j))

    # ------------------------------------------------------------ composition

    @property
    def model_id(self) -> str:
        """The model this patch belongs to (see the module docstring)."""
        return BUILTIN_ID if self.robot is None else self.robot.model_id

    def check_model(self, model_id: str | None, source: str = "patch") -> None:
        """Raise :class:`PatchError` unless this patch belongs to model ``model_id``."""
        if self.effects and not same_model(self.model_id, model_id):
            raise PatchError(f"{source}: this patch was fitted on model {self.model_id}, not on "
                             f"{model_id or BUILTIN_ID}; fit a patch on this model instead")

    def with_effect(self, effect: str, joints, values) -> "ModelPatch":
        return ModelPatch(self.effects + (EffectInstance(effect, tuple(joints), values, robot=self.robot),), self.robot)

    def __add__(self, other: "ModelPatch") -> "ModelPatch":
        if self.effects and other.effects:
            other.check_model(self.model_id)
        return ModelPatch(self.effects + other.effects, self.robot if self.robot is not None else other.robot)

    def updated(self, other: "ModelPatch") -> "ModelPatch":
        """This patch with ``other``'s (effect, joint) entries replacing its own, ``other``'s effects last.

        Replacing, not composing: ``other``'s values are the values (a fit's new estimate, a
        patch file's entry over another's). To put ``other`` *on top of* this patch — a
        randomization draw around a patched robot — use :meth:`composed`."""
        if self.effects and other.effects:
            other.check_model(self.model_id)
        taken: dict[str, set[str]] = {}
        for e in other.effects:
            taken.setdefault(e.effect, set()).update(e.joints)
        kept = []
        for e in self.effects:
            rest = e.without(taken[e.effect]) if e.effect in taken else e
            if rest is not None:
                kept.append(rest)
        return ModelPatch(tuple(kept) + other.effects, self.robot if self.robot is not None else other.robot)

    def composed(self, other: "ModelPatch") -> "ModelPatch":
        """``other`` acting on top of this patch: on an (effect, joint) both carry, the values
        compose as the effect's parameters say (:attr:`~adadex.sim.effects.Param.composition`) —
        scales multiply (``kp_scale`` 0.3 composed with 1.05 is 0.315; ``mass_scale``,
        ``damping_scale``, ``torque_limit`` likewise), offsets add (``damping`` 0.2 composed with
        0.05 is 0.25; ``armature``, ``payload_mass``, delays, lags, encoder offsets likewise) — and
        the result is clipped to the effect's bounds on that joint. Entries only one side carries
        keep their value. Effect order as :meth:`updated` (``other``'s effects last); a composed
        entry loses its ``ci95`` (the interval was of one side's value alone).

        This is how :class:`~adadex.envs.tracking.TrackingEnv` puts a world's randomization draw on
        its patch (:meth:`adadex.envs.randomization.Randomization.world_patch`).
        """
        if self.effects and other.effects:
            other.check_model(self.model_id)
        robot = self.robot if self.robot is not None else other.robot
        mine = {(e.effect, j): (e, i) for e in self.effects for i, j in enumerate(e.joints)}
        composed = []
        for e in other.effects:
            hit = [i for i, j in enumerate(e.joints) if (e.effect, j) in mine]
            if not hit:
                composed.append(e)
                continue
            values = e.values.copy()
            for i in hit:
                own, k = mine[(e.effect, e.joints[i])]
                for p, how in enumerate(e.spec.compositions):
                    a, b = own.values[k, p], e.values[i, p]
                    values[i, p] = a * b if how == "scale" else a + b
            lo, hi = e.spec.bounds(e.joints, robot)
            composed.append(EffectInstance(e.effect, e.joints, np.clip(values, lo, hi), None, robot))
        return self.updated(ModelPatch(tuple(composed), robot))

    def stage(self, *stages: str) -> "ModelPatch":
        """The effects acting at ``stages`` (``"model"``, ``"structure"``, ``"command"``, ``"sensor"``)."""
        return ModelPatch(tuple(e for e in self.effects if e.spec.stage in stages), self.robot)

    def content_key(self) -> str:
        """Canonical JSON of what this patch does to a compiled model (its active model- and
        structure-stage effects, in order; intervals left out): equal keys, equal models."""
        effects = [e.to_dict() for e in self.active().effects if e.spec.stage in ("model", "structure")]
        for d in effects:
            d.pop("ci95", None)
        return json.dumps(effects, sort_keys=True)

    def active(self) -> "ModelPatch":
        """The patch without effects at their absent values."""
        return ModelPatch(tuple(e for e in self.effects if not e.is_absent()), self.robot)

    def __len__(self) -> int:
        return len(self.effects)

    # ------------------------------------------------------------ application

    def edit_spec(self, spec: mujoco.MjSpec) -> None:
        """Structural edits (history buffers, activations) before compiling."""
        for e in self.active().effects:
            e.spec.edit_spec(spec, list(e.joints), e.values, spec.option.timestep)

    def apply_model(self, model: mujoco.MjModel, base: ModelBase | None = None) -> None:
        """Set every effect's parameters on ``model`` as absolute values from ``base``: scale
        effects first re-size a copy of ``base`` (and write it), the others act on top of it."""
        base = base if base is not None else ModelBase.of(model)
        active = self.active().effects
        scales = [e for e in active if e.spec.rescales]
        if scales:
            base = base.copy()
            for e in scales:
                e.spec.rescale(base, model, e.jid, e.values)
        for e in scales + [e for e in active if not e.spec.rescales]:
            e.spec.apply_model(model, base, e.jid, e.values)

    def transform_command(self, command: np.ndarray, dt: float) -> np.ndarray:
        for e in self.active().effects:
            command = e.spec.transform_command(command, e.jid, e.values, dt)
        return command

    def transform_measurement(self, qpos: np.ndarray) -> np.ndarray:
        for e in self.active().effects:
            qpos = e.spec.transform_measurement(qpos, e.jid, e.values)
        return qpos

    def build_model(self, object_name: str | None = None, *, timestep: float | None = None) -> mujoco.MjModel:
        """The scene (robot + table + optional object) with this patch applied: a copy of
        :func:`patched_scene`'s model, the caller's to edit."""
        opts = PhysicsOptions() if timestep is None else PhysicsOptions(timestep=timestep)
        return copy.copy(patched_scene(object_name, self, options=opts))

    # ------------------------------------------------------------ files

    def to_dict(self) -> dict:
        return {"version": PATCH_VERSION, "model": self.model_id, "effects": [e.to_dict() for e in self.effects]}

    @classmethod
    def from_dict(cls, d: dict, *, source: str = "patch", robot=None) -> "ModelPatch":
        """Read a patch; ``robot`` is the joint table of the model it must belong to (None: built-in)."""
        if not isinstance(d, dict) or not isinstance(d.get("effects"), list):
            raise PatchError(f"{source}: expected an object with an 'effects' list")
        if d.get("version", PATCH_VERSION) != PATCH_VERSION:
            raise PatchError(f"{source}: unsupported patch version {d.get('version')!r} (this adadex reads {PATCH_VERSION})")
        model = d.get("model", BUILTIN_ID)
        expected = BUILTIN_ID if robot is None else robot.model_id
        if d["effects"] and not same_model(model, expected):
            raise PatchError(f"{source}: this patch was fitted on model {model}, not on {expected}; "
                             "a patch is only valid on the model it was fitted on")
        robot = None if robot is None or robot.builtin else robot
        effects = []
        for i, entry in enumerate(d["effects"]):
            try:
                effects.append(EffectInstance.from_dict(entry, robot))
            except (EffectError, PatchError, KeyError) as e:
                msg = e.args[0] if e.args else str(e)
                raise PatchError(f"{source}: effects[{i}]: {msg}") from None
        try:
            return cls(tuple(effects), robot)
        except PatchError as e:
            raise PatchError(f"{source}: {e}") from None

    def save(self, path: str | os.PathLike) -> Path:
        """Write JSON atomically (temp file in the same folder, then rename)."""
        return atomic_write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike, *, robot=None) -> "ModelPatch":
        """Read a patch file; it must belong to ``robot``'s model (None: the built-in robot)."""
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except FileNotFoundError:
            raise PatchError(f"{path}: no such patch file") from None
        except json.JSONDecodeError as e:
            raise PatchError(f"{path}: not valid JSON ({e})") from None
        return cls.from_dict(d, source=str(path), robot=robot)

    def describe(self) -> str:
        if not self.effects:
            return "(no effects)"
        parts = []
        for e in self.effects:
            vals = ", ".join(f"{j}: " + "/".join(f"{v:.4g}" for v in row) for j, row in zip(e.joints, e.values))
            parts.append(f"{e.effect}({'/'.join(e.spec.param_names)}) {vals}")
        return "; ".join(parts)


#: Compiled scenes :func:`patched_scene` keeps (least recently used dropped first).
SCENE_CACHE_SIZE = 128


def patched_scene(object_name: str | None = None, patch: ModelPatch | None = None, *,
                  uniform_layout: bool = False, object_scale: float = 1.0,
                  options: PhysicsOptions = PhysicsOptions()) -> mujoco.MjModel:
    """The scene of :func:`~adadex.sim.scene.build_scene_spec` with ``patch`` applied: structural
    edits before compiling, parameters after (absolute values from the compiled model).

    Compiled once per (scene arguments, :meth:`ModelPatch.content_key`) and kept in a bounded
    cache (:data:`SCENE_CACHE_SIZE`): two patches with the same effects and values share a model,
    whatever file they came from. The returned model is shared — treat it as read-only and
    ``copy.copy`` it before editing parameters (per-world randomization, fitting do).

    Args:
        object_name: the object on the table; None (default): no object.
        patch: the effects to apply (None: none, the nominal scene).
        uniform_layout: pad the object's geoms to the shared layout (see ``build_scene_spec``).
        object_scale: uniform scale factor of the object (default 1.0).
        options: the solver settings (:class:`~adadex.sim.scene.PhysicsOptions`).

    Returns:
        the compiled, shared ``mujoco.MjModel``.
    """
    key = (patch or ModelPatch()).content_key()
    return _compiled_scene(object_name, key, bool(uniform_layout), float(object_scale), options)


@functools.lru_cache(maxsize=SCENE_CACHE_SIZE)
def _compiled_scene(object_name, key: str, uniform_layout: bool, object_scale: float,
                    options: PhysicsOptions) -> mujoco.MjModel:
    patch = ModelPatch.from_dict({"effects": json.loads(key)})
    spec = build_scene_spec(object_name, uniform_layout=uniform_layout, object_scale=object_scale, options=options)
    patch.edit_spec(spec)
    model = spec.compile()
    patch.apply_model(model)
    return model
