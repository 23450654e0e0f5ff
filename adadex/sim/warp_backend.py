"""B worlds of a scene stepped together on a GPU (or Warp's CPU device) through MuJoCo Warp.

:class:`WarpSim` has :class:`~adadex.sim.batched.BatchedSim`'s interface and semantics —
``reset(qpos, qvel, worlds)``, ``step(ctrl) -> SimReadout`` (``substeps`` physics steps with the
control held), ``readout()``, ``models``, ``set_models``, ``set_state``, ``close`` — but keeps every
world's state in MuJoCo Warp's device arrays, so a step costs no host round trip on a GPU beyond
reading the overflow counters. Select it with ``BatchedSim(models, backend="warp")`` or
``TrackingEnv(..., backend="warp")`` (which then steps on the sim's device too) or the recipes'
``sim.backend=warp``; it needs the optional extra: ``pip install "adadex[warp]"``.

What it takes to match the rollout backend (tested against it on Warp's CPU device):

* **Contact and constraint capacity** is fixed when the device data is made: ``nconmax`` contacts
  and ``njmax`` constraint rows per world (:data:`DEFAULT_NCONMAX`, :data:`DEFAULT_NJMAX`; a
  pinch grasp needs ~17 contacts: ``njmax=64`` drops constraints and the object slips). MuJoCo
  Warp drops what does not fit and only sets a flag, so ``step`` reads the flags after every
  control step. Never silently:

  - the contact buffers are shared by all worlds (``nconmax × B``): an overflow there **raises** a
    :class:`~adadex.errors.ConfigError` naming ``nconmax`` (no world can be blamed alone);
  - constraint rows are per world: a world that needed more than ``njmax`` is **flagged unstable**
    (its own physics is wrong, the others are not), counted in :attr:`WarpSim.overflow_count`, and
    must be reset like a diverged world (a reset clears its flag). A diverging world typically
    overflows first; healthy worlds never do at the default size (tested on the scripted grasp).
* **Per-world parameters**: worlds whose models share one structure but differ in parameters (the
  effects of :mod:`adadex.sim.effects`, :class:`~adadex.envs.randomization.Randomization`'s draws)
  run with their own values: the model is put on the device with those fields batched per world
  (:data:`DEFAULT_BATCHED_FIELDS`, plus any other batchable field in which the worlds differ), and
  ``set_models`` writes a world's new values into them (a field batched for the first time puts
  the model on the device again). A field MuJoCo Warp cannot batch (geom types, solver options,
  the contact filters of a geom both worlds collide with …) must be equal in every world, else a
  ``ConfigError`` names it — it is never silently taken from world 0. Not compared, because
  stepping never reads them: keyframes, ``geom_group`` without ray sensors, ``dof_length``
  without sleeping.
* **Different objects per world** (uniform-layout scenes, any object at any size): MuJoCo Warp
  shares mesh data between worlds, so every distinct mesh of the worlds' models goes into one
  :class:`MeshPool` and each world points its object geoms at its own meshes (``geom_dataid``
  per world). Collision pairs are fixed when the model is put on the device, so every geom slot
  some world's object uses is made colliding, and a world whose object has fewer parts parks the
  slots it leaves unused (:data:`PARKED_MARGIN`: never touching anything); the pads' mass is in
  that world's own body mass. Worlds of 1-, 16- and 21-part objects and a resized mug rest as in
  their own rollout models (tested).
* **Stability**: MuJoCo Warp neither resets a diverging world nor stops its (float32) time, so the
  ``unstable`` mask is the backend's own check: a non-finite or absurd (> 1e10, MuJoCo's
  ``mjMAXVAL``) position, velocity or activation, or a time that did not advance by the control
  step. The world's state is left as it is for the caller to reset (a TrackingEnv resets it alone).
* **Warmstart**: each world's solver warmstarts from its previous physics step, across control
  steps (zeroing it per control step made the scripted grasp drift 1 mm from the rollout backend;
  keeping it agrees to 15 µm); a reset world starts cold.

The physics runs in float32 on the device (MuJoCo runs float64): joint angles agree to ~1e-6 rad
after a second of motion, contacts to ~1e-4 (see ``tests/sim/test_warp_backend.py``).

Readouts: :meth:`WarpSim.step` and :meth:`WarpSim.readout` return the numpy
:class:`~adadex.sim.batched.SimReadout` (float64, host copies) like BatchedSim;
:meth:`WarpSim.device_readout` returns a :class:`DeviceReadout` of torch tensors on the device
(float32, no host copy) for an on-device env or a benchmark; :meth:`WarpSim.step_device` steps and
returns it. ``step`` accepts a numpy array or a torch tensor (on any device).

Kernels compile on first use (about two minutes on 2 busy CPU cores, cached by Warp afterwards in
``wp.config.kernel_cache_dir``, ``WARP_CACHE_PATH``). On a CUDA device the ``substeps`` physics steps
of a control step are captured once into a CUDA graph and replayed (``cuda_graph=True``), and Warp's
stream and torch's are ordered by events both ways (run on an H100: see ``docs/gpu.md``; CI tests Warp's
CPU device).

Example::

    import numpy as np
    from adadex.sim.scene import build_scene_model, home_state
    from adadex.sim.batched import BatchedSim
    model = build_scene_model("box_00")
    sim = BatchedSim(model, batch_size=4, backend="warp")     # Warp's default device
    qpos, ctrl = home_state(model)
    sim.reset(qpos=qpos)
    out = sim.step(np.tile(ctrl, (4, 1)))                       # numpy SimReadout
    dev = sim.device_readout()                                  # torch tensors on the device
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from adadex.errors import ArrayError, ConfigError
from adadex.sim.readout import FULLPHYSICS, SimReadout, control_substeps, reset_states, world_models
from adadex.sim.robot import NUM_JOINTS, TRACKED_SITES

#: Contacts per world allocated on the device (MuJoCo Warp shares them across worlds:
#: ``naconmax = nconmax * B``). A pinch grasp makes ~17; the table, fingers and object rarely 40.
DEFAULT_NCONMAX = 64
#: Constraint rows per world (contacts × cone rows, joint limits, friction loss). MuJoCo Warp's own
#: default (64 here) overflows during a grasp; 192 was measured enough, 256 leaves a margin.
DEFAULT_NJMAX = 256
#: MuJoCo's ``mjMAXVAL``: a position, velocity or activation beyond it means a diverged world.
MAX_STATE_VALUE = 1e10

#: Model fields batched per world from the start: every field an effect or a randomization draw
#: changes (:class:`adadex.sim.effects.ModelBase`), and the constants ``mj_setConst`` derives from
#: masses. Another batchable field in which worlds differ is batched when it first differs.
DEFAULT_BATCHED_FIELDS = (
    "dof_damping", "dof_frictionloss", "dof_armature", "jnt_stiffness",
    "actuator_gainprm", "actuator_biasprm", "actuator_forcerange", "jnt_actfrcrange",
    "actuator_delay", "actuator_dynprm",
    "body_mass", "body_inertia", "body_subtreemass", "body_invweight0", "dof_invweight0", "actuator_acc0",
    "geom_friction", "geom_solref",
)

_INSTALL = 'pip install "adadex[warp]"'


def _import_warp():
    """``(warp, mujoco_warp)``, or a ConfigError saying how to install them."""
    try:
        import mujoco_warp
        import warp
    except ImportError as e:
        raise ConfigError(f'backend="warp" needs MuJoCo Warp, which is not installed ({e}); install the '
                          f'optional extra: {_INSTALL}') from e
    return warp, mujoco_warp


def torch_device(device=None) -> torch.device:
    """The torch device of Warp device ``device`` (a Warp or torch name; ``None``: Warp's default device,
    a GPU when there is one) — where a ``WarpSim`` on it keeps its tensors."""
    wp, _ = _import_warp()
    wp.init()
    try:
        d = wp.get_device(None if device is None else str(device))
    except (ValueError, RuntimeError) as e:
        raise ConfigError(f"device={str(device)!r}: not a Warp device here ({e})") from e
    return torch.device(wp.device_to_torch(d))


def warp_available() -> bool:
    """Whether MuJoCo Warp (the ``[warp]`` extra) is importable."""
    try:
        _import_warp()
    except ConfigError:
        return False
    return True


@dataclass
class DeviceReadout:
    """:class:`~adadex.sim.batched.SimReadout`'s fields as float32 torch tensors on the sim's device
    (new tensors each call: they do not alias the simulation's state)."""

    time: torch.Tensor          # (B,)
    joint_pos: torch.Tensor     # (B, 22)
    joint_vel: torch.Tensor     # (B, 22)
    link_pose: torch.Tensor     # (B, 5, 7)
    object_pose: torch.Tensor   # (B, 7); zeros without an object
    object_vel: torch.Tensor    # (B, 6)
    unstable: torch.Tensor      # (B,) bool

    def numpy(self) -> SimReadout:
        """The host :class:`SimReadout` (float64)."""
        f = {k: getattr(self, k).detach().cpu().numpy() for k in self.__dataclass_fields__}
        return SimReadout(**{k: (v if k == "unstable" else v.astype(np.float64)) for k, v in f.items()})


def _field_specs(mjw):
    """(batchable, shared) names of MuJoCo Warp ``Model`` array fields that are ``MjModel`` attributes."""
    from mujoco_warp._src import types, warp_util

    batchable, shared = [], []
    probe = mujoco.MjModel  # attribute names only
    for f in dataclasses.fields(types.Model):
        if not warp_util.is_array_spec(f.type) or not hasattr(probe, f.name):
            continue
        shape = getattr(f.type, "shape", ())
        (batchable if shape and shape[0] == "*" else shared).append(f.name)
    return tuple(batchable), tuple(shared)


_OPT_FIELDS = ("timestep", "tolerance", "ls_tolerance", "noslip_tolerance", "ccd_tolerance", "gravity", "wind",
               "magnetic", "density", "viscosity", "impratio", "o_margin", "o_solref", "o_solimp", "o_friction",
               "integrator", "cone", "jacobian", "solver", "iterations", "ls_iterations", "noslip_iterations",
               "ccd_iterations", "disableflags", "enableflags", "sdf_initpoints", "sdf_iterations")

#: Non-batchable limit flags that have an equivalent through their batchable range: a world without
#: the limit gets the flag with an infinite range.
_LIMIT_FLAGS = {"actuator_forcelimited": "actuator_forcerange", "jnt_actfrclimited": "jnt_actfrcrange"}


#: Geom fields of a slot (one geom index) that only matter where the slot collides: a world whose
#: model leaves a slot non-colliding (a pad) may hold anything there.
_SLOT_FIELDS = ("geom_contype", "geom_conaffinity", "geom_condim", "geom_priority")
#: Shared model fields never read while stepping (keyframes are applied on the host).
_IGNORED = frozenset({"key_time", "key_qpos", "key_qvel", "key_act", "key_mpos", "key_mquat", "key_ctrl",
                      "key_plastic"})


def _fields_bytes(m: mujoco.MjModel, fields: Sequence[str]) -> bytes:
    """``m``'s values of ``fields`` as one byte string (equal models, equal strings; for a fast check)."""
    return b"".join(np.ascontiguousarray(getattr(m, f)).tobytes() for f in fields)


def _active_slots(m: mujoco.MjModel) -> np.ndarray:
    """(ngeom,) which geoms can collide in ``m``."""
    return (np.asarray(m.geom_contype) != 0) | (np.asarray(m.geom_conaffinity) != 0)


def _sleeps(m: mujoco.MjModel) -> bool:
    """Whether sleeping is on (then ``dof_length``, which scales the sleep test, matters)."""
    return bool(m.opt.enableflags & int(mujoco.mjtEnableBit.mjENBL_SLEEP))


def _has_rays(m: mujoco.MjModel) -> bool:
    """Whether a sensor casts rays (then ``geom_group``, which rays filter on, matters)."""
    return bool(np.isin(m.sensor_type, [int(mujoco.mjtSensor.mjSENS_RANGEFINDER)]).any())


#: ``geom_margin`` of a geom slot a world does not use (a pad of a smaller object, see
#: :func:`adadex.sim.objects.add_object_geoms`): margins add up, and MuJoCo Warp's plane and
#: oriented-box broadphase filters reject any pair whose summed margin is this negative, so the slot
#: never touches anything in that world (it is not moved: its mass is already in the world's body).
PARKED_MARGIN = -1.0e4

_MESH_FIELDS = ("mesh_vertadr", "mesh_vertnum", "mesh_faceadr", "mesh_normaladr", "mesh_normalnum", "mesh_graphadr",
                "mesh_vert", "mesh_normal", "mesh_face", "mesh_graph", "mesh_pos", "mesh_quat", "mesh_polynum",
                "mesh_polyadr", "mesh_polynormal", "mesh_polyvertadr", "mesh_polyvertnum", "mesh_polyvert",
                "mesh_polymapadr", "mesh_polymapnum", "mesh_polymap", "mesh_octadr")


class MeshPool:
    """Every distinct mesh of the worlds' models, concatenated into MuJoCo Warp's mesh arrays.

    MuJoCo Warp shares mesh data between worlds but lets each world choose a geom's mesh
    (``geom_dataid`` is batchable), so worlds holding different objects (or one object at different
    sizes) point their object geoms at their own meshes in one pool. Meshes are taken from the
    compiled models as they are (convex hull graph and polygons included: MuJoCo builds them for the
    colliding geoms that use them) and keyed by content, so a mesh shared by many worlds is stored
    once. The pool grows when a model with a new mesh arrives (``set_models``)."""

    def __init__(self):
        self._index: dict[bytes, int] = {}
        self._meshes: list[dict] = []
        self.npolygonmax = 0
        self.nmeshdegmax = 0
        self._maps: dict[int, tuple[mujoco.MjModel, np.ndarray]] = {}
        # arrays() so far: the pool grows by appending, so only new meshes are laid out again
        self._parts: dict[str, list] = {f: [] for f in _MESH_FIELDS}
        self._laid_out = 0
        self._ends = (0,) * 7        # vert, normal, face, graph, poly, polyvert, polymap entries so far

    def __len__(self) -> int:
        return len(self._meshes)

    @staticmethod
    def _mesh(m: mujoco.MjModel, i: int) -> dict:
        va, vn = int(m.mesh_vertadr[i]), int(m.mesh_vertnum[i])
        fa, fn = int(m.mesh_faceadr[i]), int(m.mesh_facenum[i])
        na, nn = int(m.mesh_normaladr[i]), int(m.mesh_normalnum[i])
        pa, pn = int(m.mesh_polyadr[i]), int(m.mesh_polynum[i])
        ga = int(m.mesh_graphadr[i])
        graph = None
        if ga >= 0:
            nv, nf = int(m.mesh_graph[ga]), int(m.mesh_graph[ga + 1])
            graph = m.mesh_graph[ga:ga + 2 + 3 * nv + 6 * nf].copy()
        pvadr, pvnum = m.mesh_polyvertadr[pa:pa + pn], m.mesh_polyvertnum[pa:pa + pn]
        pmadr, pmnum = m.mesh_polymapadr[va:va + vn], m.mesh_polymapnum[va:va + vn]
        return dict(
            vert=m.mesh_vert[va:va + vn].copy(), normal=m.mesh_normal[na:na + nn].copy(),
            face=m.mesh_face[fa:fa + fn].copy(), graph=graph, pos=m.mesh_pos[i].copy(), quat=m.mesh_quat[i].copy(),
            polynormal=m.mesh_polynormal[pa:pa + pn].copy(), polyvertnum=pvnum.copy(),
            polyvert=np.concatenate([m.mesh_polyvert[a:a + n] for a, n in zip(pvadr, pvnum)] or [np.zeros(0, int)]),
            polymapnum=pmnum.copy(),
            polymap=np.concatenate([m.mesh_polymap[a:a + n] for a, n in zip(pmadr, pmnum)] or [np.zeros(0, int)]))

    def ids(self, m: mujoco.MjModel) -> np.ndarray:
        """(ngeom,) ``geom_dataid`` of ``m`` in the pool (meshes added as needed); other geoms keep theirs."""
        hit = self._maps.get(id(m))
        if hit is not None and hit[0] is m:
            return hit[1]
        local = np.full(m.nmesh, -1)
        for i in range(m.nmesh):
            va, vn = int(m.mesh_vertadr[i]), int(m.mesh_vertnum[i])
            fa, fn = int(m.mesh_faceadr[i]), int(m.mesh_facenum[i])
            key = (m.mesh_vert[va:va + vn].tobytes() + m.mesh_face[fa:fa + fn].tobytes()
                   + m.mesh_pos[i].tobytes() + m.mesh_quat[i].tobytes())
            j = self._index.get(key)
            if j is None:
                j = self._index[key] = len(self._meshes)
                self._meshes.append(self._mesh(m, i))
            local[i] = j
        self.npolygonmax = max(self.npolygonmax, int(m.npolygonmax))
        self.nmeshdegmax = max(self.nmeshdegmax, int(m.nmeshdegmax))
        out = np.asarray(m.geom_dataid).copy()
        is_mesh = (m.geom_type == int(mujoco.mjtGeom.mjGEOM_MESH)) & (out >= 0)
        out[is_mesh] = local[out[is_mesh]]
        if len(self._maps) > 512:
            self._maps.clear()
        self._maps[id(m)] = (m, out)
        return out

    def arrays(self) -> dict[str, np.ndarray]:
        """The pool as MuJoCo Warp's ``mesh_*`` arrays (addresses rebased, indices stay per mesh); meshes
        laid out by an earlier call are not laid out again."""
        out = self._parts
        v, n, fc, g, p, pv, pm = self._ends
        for mesh in self._meshes[self._laid_out:]:
            nv, nn, nf, npoly = len(mesh["vert"]), len(mesh["normal"]), len(mesh["face"]), len(mesh["polynormal"])
            out["mesh_vertadr"].append([v]), out["mesh_vertnum"].append([nv])
            out["mesh_normaladr"].append([n]), out["mesh_normalnum"].append([nn])
            out["mesh_faceadr"].append([fc])
            out["mesh_graphadr"].append([g if mesh["graph"] is not None else -1])
            out["mesh_vert"].append(mesh["vert"]), out["mesh_normal"].append(mesh["normal"])
            out["mesh_face"].append(mesh["face"])
            if mesh["graph"] is not None:
                out["mesh_graph"].append(mesh["graph"])
                g += len(mesh["graph"])
            out["mesh_pos"].append(mesh["pos"][None]), out["mesh_quat"].append(mesh["quat"][None])
            out["mesh_polynum"].append([npoly]), out["mesh_polyadr"].append([p])
            out["mesh_polynormal"].append(mesh["polynormal"]), out["mesh_polyvertnum"].append(mesh["polyvertnum"])
            out["mesh_polyvertadr"].append(pv + np.concatenate([[0], np.cumsum(mesh["polyvertnum"])[:-1]])
                                           if npoly else np.zeros(0, int))
            out["mesh_polyvert"].append(mesh["polyvert"])
            out["mesh_polymapnum"].append(mesh["polymapnum"])
            out["mesh_polymapadr"].append(pm + np.concatenate([[0], np.cumsum(mesh["polymapnum"])[:-1]]))
            out["mesh_polymap"].append(mesh["polymap"])
            out["mesh_octadr"].append([-1])
            v, n, fc, p = v + nv, n + nn, fc + nf, p + npoly
            pv += len(mesh["polyvert"])
            pm += len(mesh["polymap"])
        self._laid_out, self._ends = len(self._meshes), (v, n, fc, g, p, pv, pm)
        for f, parts in out.items():       # one array per field, kept as the head of the next call's list
            if len(parts) > 1:
                out[f] = [np.concatenate([np.asarray(a) for a in parts])]
        return {f: np.asarray(parts[0]) if parts else np.zeros(0) for f, parts in out.items()}


class WarpSim:
    """B worlds stepped together by MuJoCo Warp; see the module docstring.

    Args:
        models: one ``MjModel`` shared by all worlds, or a sequence of B models of one structure.
        batch_size: B (inferred from ``models`` when it is a sequence).
        substeps: physics steps per control step (default: one 12 Hz control step).
        device: Warp device (``"cpu"``, ``"cuda:0"`` …); default Warp's default device.
        nconmax: contacts per world allocated on the device; an overflow raises a ConfigError.
        njmax: constraint rows per world; a world that overflows them is flagged unstable.
        nthread: accepted for BatchedSim's signature, unused.
        cuda_graph: on a CUDA device, replay each control step as a captured CUDA graph.
    """

    def __init__(self, models: mujoco.MjModel | Sequence[mujoco.MjModel], batch_size: int | None = None, *,
                 substeps: int | None = None, device=None, nconmax: int = DEFAULT_NCONMAX,
                 njmax: int = DEFAULT_NJMAX, nthread: int = 0, cuda_graph: bool = True):
        wp, mjw = _import_warp()
        self._wp, self._mjw = wp, mjw
        self._models = world_models(models, batch_size)
        for name, v in (("nconmax", nconmax), ("njmax", njmax)):
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise ConfigError(f"{name} must be a positive integer, got {v!r}")
        m0 = self._models[0]
        substeps = control_substeps(m0, substeps)
        self.batch_size = len(self._models)
        self.nthread = nthread
        self.substeps = int(substeps)
        self.timestep = float(m0.opt.timestep)
        self.nconmax, self.njmax = int(nconmax), int(njmax)
        self.nstate = mujoco.mj_stateSize(m0, FULLPHYSICS)
        self._has_object = m0.nq > NUM_JOINTS
        self._batchable, self._shared = _field_specs(mjw)
        # The device model is world 0's with two kinds of edits (the "template"): geom slots that some
        # world uses (a larger object's parts) are made colliding, and limit flags that some world sets
        # are on (see _compare). Every world's own values go into the batched fields.
        self._template = copy.copy(m0)
        self._batched = {f for f in DEFAULT_BATCHED_FIELDS if f in self._batchable} | {"geom_dataid", "geom_margin"}
        self._checked: dict[int, mujoco.MjModel] = {}
        self._fields_key, self._fields_cache = None, ((), ())   # _compared_fields
        self._bytes_cache: dict = {}                             # _template_bytes
        for i, m in enumerate(self._models):
            self._adopt(m, f"model {i}")
        self._pool = MeshPool()
        for m in self._models:
            self._pool.ids(m)

        wp.init()
        self.device = wp.get_device(device)
        self.torch_device = torch.device(wp.device_to_torch(self.device))
        self._cuda_graph = bool(cuda_graph) and self.device.is_cuda
        self._graph = None
        B = self.batch_size
        with wp.ScopedDevice(self.device):
            self._put_model()
            self._data = mjw.make_data(self._template, nworld=B, nconmax=self.nconmax, njmax=self.njmax)
            self._state_wp = wp.zeros((B, self.nstate), dtype=float)
            self._active_wp = wp.zeros(B, dtype=bool)
        self._torch_waits()
        d, T = self._data, wp.to_torch
        self._qpos, self._qvel, self._ctrl = T(d.qpos), T(d.qvel), T(d.ctrl)
        self._act = T(d.act) if m0.na else None
        self._time, self._sens = T(d.time), T(d.sensordata)
        self._warmstart, self._overflow = T(d.qacc_warmstart), T(d.overflow)
        self._state_t, self._active_t = T(self._state_wp), T(self._active_wp)
        from mujoco_warp._src.types import OverflowType
        cap = OverflowType.ALL & ~(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)
        self._capacity_bits = int(cap)
        self._world_bits = int(OverflowType.NEFC | OverflowType.NJMAX_NNZ)     # per world: that world alone
        #: worlds flagged unstable because they needed more than ``njmax`` constraint rows
        self.overflow_count = 0
        self._overflow_names = {int(OverflowType.NEFC): "njmax", int(OverflowType.NJMAX_NNZ): "njmax",
                                int(OverflowType.BROADPHASE): "nconmax", int(OverflowType.NARROWPHASE): "nconmax",
                                int(OverflowType.CCD): "nconmax"}
        adr = [int(m0.sensor_adr[m0.sensor(f"{s}_pos").id]) for s in TRACKED_SITES]
        qadr = [int(m0.sensor_adr[m0.sensor(f"{s}_quat").id]) for s in TRACKED_SITES]
        link_idx = np.array([list(range(a, a + 3)) + list(range(q, q + 4)) for a, q in zip(adr, qadr)])
        self._link_idx = torch.as_tensor(link_idx, device=self.torch_device)
        self._host_data = mujoco.MjData(max(self._models, key=lambda m: (m.nC, m.nbvh, m.nbvhdynamic)))
        self._parts = self._state_parts()
        self._closed = False
        self.reset()

    # ---------------------------------------------------------------- models

    @property
    def models(self) -> list[mujoco.MjModel]:
        return self._models

    def _compare(self, m: mujoco.MjModel, what: str) -> tuple[set, np.ndarray, dict]:
        """What the device model must change to run ``m`` in a world: (fields to batch, geom slots to
        make colliding, limit flags to turn on); a ConfigError for a difference MuJoCo Warp cannot
        hold per world (another structure, solver options, geom types or contact filters of a slot
        both use, …)."""
        t = self._template
        if m.signature != t.signature:
            raise ConfigError(f"{what} differs in structure from model 0 (signature {m.signature} != "
                              f"{t.signature}); per-world models may differ only in parameters; build scenes "
                              f"with uniform_layout=True to hold different objects")
        for name in _OPT_FIELDS:
            if hasattr(t.opt, name) and not np.array_equal(getattr(m.opt, name), getattr(t.opt, name)):
                raise ConfigError(f"{what} differs from model 0 in opt.{name}; the warp backend shares solver "
                                  f"options between worlds (they cannot be batched)")
        act_t, act_m = _active_slots(t), _active_slots(m)
        both = act_t & act_m
        plain, keyed = self._compared_fields()
        diff = []
        if _fields_bytes(m, plain) != self._template_bytes(plain):   # one comparison for the usual case
            diff = [f for f in plain if not np.array_equal(getattr(m, f), getattr(t, f))]
        for f in _SLOT_FIELDS:
            a, b = np.asarray(getattr(m, f)), np.asarray(getattr(t, f))
            if not np.array_equal(a[both], b[both]):    # a slot one of them leaves unused takes the other's values
                diff.append(f)
        if diff:
            raise ConfigError(f"{what} differs from model 0 in {', '.join(diff)}, which MuJoCo Warp cannot set per "
                              f"world; per-world models may differ only in batchable parameters")
        batch = set()
        if _fields_bytes(m, keyed) != self._template_bytes(keyed):
            batch = {f for f in keyed if not np.array_equal(getattr(m, f), getattr(t, f))}
        flags = {}
        for flag, rng in _LIMIT_FLAGS.items():
            on_m, on_t = np.asarray(getattr(m, flag)) != 0, np.asarray(getattr(t, flag)) != 0
            if (on_m & ~on_t).any():
                flags[flag] = on_m | on_t
            if (on_m != on_t).any():
                batch.add(rng)            # the range carries the difference: infinite where off
        return batch - self._batched, act_m & ~act_t, flags

    def _compared_fields(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """(shared fields every world must hold as the template does — slot fields, limit flags, meshes
        and fields never read while stepping aside —, batchable fields not batched yet)."""
        t = self._template
        key = (frozenset(self._batched), _sleeps(t), _has_rays(t))
        if self._fields_key != key:
            plain = tuple(f for f in self._shared if not (
                f in _LIMIT_FLAGS or f in _SLOT_FIELDS or f.startswith("mesh_") or f in _IGNORED
                or (f == "dof_length" and not _sleeps(t)) or (f == "geom_group" and not _has_rays(t))))
            self._fields_cache = (plain, tuple(f for f in self._batchable if f not in self._batched))
            self._fields_key = key
        return self._fields_cache

    def _template_bytes(self, fields: tuple[str, ...]) -> bytes:
        """The template's values of ``fields``, one byte string (cached until the template changes)."""
        key = (fields, id(self._template))
        if key not in self._bytes_cache:
            if len(self._bytes_cache) > 8:
                self._bytes_cache.clear()
            self._bytes_cache[key] = _fields_bytes(self._template, fields)
        return self._bytes_cache[key]

    def _adopt(self, m: mujoco.MjModel, what: str) -> bool:
        """Check ``m`` and change the template to hold it; whether the device model must be put again."""
        hit = self._checked.get(id(m))
        if hit is m:
            return False
        batch, slots, flags = self._compare(m, what)
        t = self._template
        if slots.any() or flags:
            self._bytes_cache.clear()      # the template's values change
        for f in _SLOT_FIELDS:
            getattr(t, f)[slots] = getattr(m, f)[slots]
        for flag, on in flags.items():
            getattr(t, flag)[:] = on
        self._batched |= batch
        changed = bool(batch or slots.any() or flags)
        if not changed:
            if len(self._checked) > 512:
                self._checked.clear()
            self._checked[id(m)] = m
        return changed

    def _world_value(self, m: mujoco.MjModel, field: str) -> np.ndarray:
        """``field`` of ``m`` as the device model runs it: mesh ids in the pool; geom slots ``m`` leaves
        unused parked (:data:`PARKED_MARGIN`); a range whose limit flag is off in ``m`` but on in the
        device model infinite (the flag is shared, the range per world)."""
        t = self._template
        if field == "geom_dataid":
            return self._pool.ids(m)
        v = np.asarray(getattr(m, field))
        if field == "geom_margin":
            parked = _active_slots(t) & ~_active_slots(m)
            if parked.any():
                v = v.copy()
                v[parked] = PARKED_MARGIN
        for flag, rng in _LIMIT_FLAGS.items():
            if rng == field:
                off = (np.asarray(getattr(m, flag)) == 0) & (np.asarray(getattr(t, flag)) != 0)
                if off.any():
                    v = v.copy()
                    v[off] = (-np.inf, np.inf)
        return v

    def _put_model(self) -> None:
        """Put the template on the device with the batched fields per world, the mesh pool in place
        of its meshes, then write every world's values."""
        wp, mjw = self._wp, self._mjw
        with wp.ScopedDevice(self.device):
            self._model = mjw.put_model(self._template,
                                        batch_sizes={f: self.batch_size for f in sorted(self._batched)})
        self._model.opt.warn_overflow = 0      # overflows are checked after every step (see _check_overflow)
        self._fields = {f: wp.to_torch(getattr(self._model, f)) for f in sorted(self._batched)}
        self._upload_meshes()
        self._write_params(range(self.batch_size), self._models)

    def _upload_meshes(self) -> None:
        """The pool's meshes as the device model's mesh arrays (replacing world 0's)."""
        wp, mm = self._wp, self._model
        arrays = self._pool.arrays()
        for f, host in arrays.items():
            dtype = getattr(mm, f).dtype
            scalar = wp.dtype_to_numpy(getattr(dtype, "_wp_scalar_type_", dtype))
            setattr(mm, f, wp.array(np.ascontiguousarray(host, dtype=scalar), dtype=dtype, device=self.device)
                    if host.size else wp.zeros(0, dtype=dtype, device=self.device))
        mm.nmesh = len(self._pool)
        for n, f in (("nmeshvert", "mesh_vert"), ("nmeshnormal", "mesh_normal"), ("nmeshface", "mesh_face"),
                     ("nmeshgraph", "mesh_graph"), ("nmeshpoly", "mesh_polynormal"),
                     ("nmeshpolyvert", "mesh_polyvert"), ("nmeshpolymap", "mesh_polymap")):
            setattr(mm, n, len(arrays[f]))
        mm.npolygonmax = max(int(mm.npolygonmax), self._pool.npolygonmax)
        mm.nmeshdegmax = max(int(mm.nmeshdegmax), self._pool.nmeshdegmax)
        self._pool_size = len(self._pool)
        self._graph = None
        self._torch_waits()

    def _write_params(self, worlds, models) -> None:
        worlds = list(worlds)
        idx = torch.as_tensor(worlds, dtype=torch.long, device=self.torch_device)
        for f, t in self._fields.items():
            host = np.stack([self._world_value(m, f) for m in models])
            t[idx] = torch.from_numpy(host.reshape((len(worlds),) + tuple(t.shape[1:]))).to(
                device=self.torch_device, dtype=t.dtype)

    def set_models(self, worlds: Sequence[int], models: Sequence[mujoco.MjModel]) -> None:
        """Give ``worlds`` new models (same structure: another object of a uniform-layout scene, or other
        parameters) and write their values to the device. Reset those worlds afterwards; their state is
        not converted. A model needing a change of the shared device model (a parameter batched for the
        first time, a geom slot no world used before) puts the model on the device again (slow, rare)."""
        worlds = [int(w) for w in worlds]
        models = list(models)
        if len(worlds) != len(models):
            raise ConfigError(f"{len(worlds)} worlds but {len(models)} models")
        for w in worlds:
            if not 0 <= w < self.batch_size:
                raise IndexError(f"world {w} out of range for batch_size={self.batch_size}")
        template = copy.copy(self._template), set(self._batched)
        try:
            reput = [self._adopt(m, f"model for world {w}") for w, m in zip(worlds, models)]
        except ConfigError:
            self._template, self._batched = template     # nothing changed
            self._bytes_cache.clear()
            raise
        for w, m in zip(worlds, models):
            self._models[w] = m
            self._pool.ids(m)
        if any(reput):
            self._put_model()
        else:
            if len(self._pool) != self._pool_size:
                self._upload_meshes()
            self._write_params(worlds, models)

    # ---------------------------------------------------------------- state

    def _worlds(self, worlds) -> np.ndarray:
        idx = np.arange(self.batch_size) if worlds is None else np.asarray(worlds, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.batch_size):
            raise IndexError(f"world indices {idx.tolist()} out of range for batch_size={self.batch_size}")
        return idx

    def reset(self, qpos: np.ndarray | None = None, qvel: np.ndarray | None = None,
              worlds: np.ndarray | Sequence[int] | None = None, ctrl: np.ndarray | None = None) -> SimReadout:
        """Reset some worlds (all by default) to ``qpos``/``qvel`` (broadcast over the reset worlds).

        As BatchedSim: positions default to each model's ``qpos0``, velocities to zero; the state and
        sensors of the reset worlds come from C MuJoCo's ``mj_forward`` on the host (a reset is not
        the hot path) and are written to the device.
        ``ctrl`` (optional, broadcast over the reset worlds): the command the worlds have been holding,
        written into the activations and history buffers of lagged and delayed actuators too
        (:func:`~adadex.sim.readout.hold_command`), so that their servos start from it, not from 0.
        """
        idx = self._worlds(worlds)
        states, sens = reset_states(self._models, self._host_data, idx, qpos, qvel, self.nstate, ctrl)
        if idx.size:
            self._write_state(idx, states)
            self._sens[torch.as_tensor(idx, device=self.torch_device)] = torch.from_numpy(sens).to(
                self.torch_device, self._sens.dtype)
        return self.readout()

    def _state_parts(self) -> list[tuple[int, int, torch.Tensor]] | None:
        """(offset in the full-physics state, size, the device data's torch view) of each component the
        state holds, in ``mj_getState``'s order; ``None`` when it holds one not mapped here (then
        MuJoCo Warp's ``set_state`` writes it)."""
        m0, d, T = self._models[0], self._data, self._wp.to_torch
        views = {mujoco.mjtState.mjSTATE_TIME: lambda: T(d.time)[:, None],
                 mujoco.mjtState.mjSTATE_QPOS: lambda: T(d.qpos), mujoco.mjtState.mjSTATE_QVEL: lambda: T(d.qvel),
                 mujoco.mjtState.mjSTATE_ACT: lambda: T(d.act),
                 mujoco.mjtState.mjSTATE_HISTORY: lambda: T(d.history)}
        parts, offset = [], 0
        for bit in range(int(mujoco.mjtState.mjNSTATE)):
            element = 1 << bit
            if not FULLPHYSICS & element:
                continue
            size = mujoco.mj_stateSize(m0, element)
            if size == 0:
                continue
            view = next((v for k, v in views.items() if int(k) == element), None)
            if view is None:
                return None
            t = view()
            if t.shape[-1] != size:
                return None
            parts.append((offset, size, t))
            offset += size
        return parts if offset == self.nstate else None

    def _write_state(self, idx: np.ndarray, states: np.ndarray) -> None:
        """Full-physics ``states`` into worlds ``idx``: through torch views of the device data (a kernel
        per component, no new Warp kernel: MuJoCo Warp's ``set_state`` builds and hashes one per call,
        milliseconds each reset), else through ``set_state``."""
        tidx = torch.as_tensor(idx, device=self.torch_device)
        values = torch.as_tensor(states).to(self.torch_device, self._state_t.dtype)
        if self._parts is not None:
            for offset, size, view in self._parts:
                view[tidx] = values[:, offset:offset + size].to(view.dtype)
        else:
            self._state_t[tidx] = values
            self._active_t.zero_()
            self._active_t[tidx] = True
            self._warp_waits()
            self._mjw.set_state(self._model, self._data, self._state_wp, FULLPHYSICS, active=self._active_wp)
            self._torch_waits()
        self._warmstart[tidx] = 0
        self._overflow[tidx] = 0

    @property
    def state(self) -> np.ndarray:
        """(B, nstate) full-physics states (``mj_getState`` layout), a host copy."""
        self._mjw.get_state(self._model, self._data, self._state_wp, FULLPHYSICS)
        self._torch_waits()
        return self._state_t.detach().cpu().numpy().astype(np.float64)

    def set_state(self, state: np.ndarray, worlds=None) -> None:
        """Overwrite full-physics states (``(B, nstate)`` or ``(len(worlds), nstate)``); sensors
        are recomputed by the next step, as in BatchedSim."""
        idx = self._worlds(worlds)
        states = np.asarray(state, dtype=np.float64).reshape(idx.size, self.nstate)
        self._write_state(idx, states)

    # ---------------------------------------------------------------- stepping

    def _torch_waits(self) -> None:
        """Order torch's work after Warp's launched so far (on a GPU they run on different streams)."""
        if self.device.is_cuda:
            wp = self._wp
            wp.stream_from_torch(torch.cuda.current_stream(self.torch_device)).wait_stream(wp.get_stream(self.device))

    def _warp_waits(self) -> None:
        """Order Warp's next launches after torch's work so far (writes through the shared tensors)."""
        if self.device.is_cuda:
            wp = self._wp
            wp.get_stream(self.device).wait_stream(wp.stream_from_torch(torch.cuda.current_stream(self.torch_device)))

    def _physics(self) -> None:
        """``substeps`` physics steps of every world: on a GPU, captured once into a CUDA graph and
        replayed (recaptured after the device model changes); if capturing fails, stepped eagerly."""
        wp, mjw = self._wp, self._mjw
        self._warp_waits()
        with wp.ScopedDevice(self.device):
            if self._graph is not None:
                wp.capture_launch(self._graph)
            else:
                for _ in range(self.substeps):
                    mjw.step(self._model, self._data)
                if self._cuda_graph:      # kernels are compiled now: record the next control steps
                    try:
                        with wp.ScopedCapture() as capture:
                            for _ in range(self.substeps):
                                mjw.step(self._model, self._data)
                        self._graph = capture.graph    # recorded, not run
                    except Exception as e:             # noqa: BLE001 - a capture failure only costs speed
                        warnings.warn(f"WarpSim: CUDA graph capture failed ({e}); stepping without graphs")
                        self._cuda_graph = False
        self._torch_waits()

    def step_device(self, ctrl) -> DeviceReadout:
        """Advance every world by one control step with ``ctrl`` (B, nu) held, returning the
        :class:`DeviceReadout` (no host copy except the overflow check)."""
        nu = self._ctrl.shape[1]
        if isinstance(ctrl, torch.Tensor):
            c = ctrl.detach()
        else:
            c = torch.from_numpy(np.asarray(ctrl, dtype=np.float64))
        if tuple(c.shape) != (self.batch_size, nu):
            raise ArrayError(f"ctrl must have shape {(self.batch_size, nu)}, got {tuple(c.shape)}")
        self._ctrl.copy_(c)
        t_expected = self._time + self.substeps * self.timestep
        self._physics()
        out = self.device_readout()
        out.unstable |= (self._time - t_expected).abs() > 0.5 * self.timestep
        out.unstable |= self._check_overflow()
        return out

    def step(self, ctrl) -> SimReadout:
        """Advance every world by one control step with ``ctrl`` (B, nu) held constant (numpy or torch)."""
        return self.step_device(ctrl).numpy()

    def _check_overflow(self) -> torch.Tensor:
        """(B,) worlds that ran out of constraint rows (``njmax``), to be flagged unstable; raises a
        ConfigError when the contact buffers (``nconmax``, shared by all worlds) overflowed."""
        flags = self._overflow & self._capacity_bits
        if not bool(flags.any()):          # the step's one device-to-host read
            return torch.zeros_like(self._time, dtype=torch.bool)
        bits = int(np.bitwise_or.reduce(flags.cpu().numpy()))
        shared = bits & ~self._world_bits
        if shared:
            settings = sorted({name for b, name in self._overflow_names.items() if shared & b}) or ["nconmax"]
            now = {"nconmax": self.nconmax, "njmax": self.njmax}
            raise ConfigError(
                f"MuJoCo Warp ran out of contact capacity in this control step (overflow flags {shared:#x}) and "
                f"dropped contacts in worlds that share the buffers, so the physics is wrong; raise "
                + " and ".join(f"{s} (now {now.get(s, '?')} per world)" for s in settings)
                + " when making the sim (BatchedSim(..., backend='warp', nconmax=..., njmax=...))")
        over = (flags & self._world_bits) != 0
        self.overflow_count += int(over.sum())
        return over

    def device_readout(self) -> DeviceReadout:
        """Current readouts of all worlds as float32 torch tensors on the device."""
        qpos, qvel = self._qpos, self._qvel
        B = self.batch_size
        if self._has_object:
            obj = qpos[:, NUM_JOINTS:NUM_JOINTS + 7].clone()
            obj_vel = qvel[:, NUM_JOINTS:NUM_JOINTS + 6].clone()
        else:
            obj = torch.zeros((B, 7), device=self.torch_device, dtype=qpos.dtype)
            obj_vel = torch.zeros((B, 6), device=self.torch_device, dtype=qpos.dtype)
        parts = [qpos, qvel] + ([self._act] if self._act is not None else [])
        unstable = torch.zeros(B, dtype=torch.bool, device=self.torch_device)
        for p in parts:
            unstable |= ~torch.isfinite(p).all(dim=1) | (p.abs() > MAX_STATE_VALUE).any(dim=1)
        unstable |= ~torch.isfinite(self._time)
        return DeviceReadout(
            time=self._time.clone(),
            joint_pos=qpos[:, :NUM_JOINTS].clone(),
            joint_vel=qvel[:, :NUM_JOINTS].clone(),
            link_pose=self._sens[:, self._link_idx],
            object_pose=obj,
            object_vel=obj_vel,
            unstable=unstable,
        )

    def readout(self) -> SimReadout:
        """Current readouts of all worlds (numpy, float64 host copies)."""
        return self.device_readout().numpy()

    def close(self) -> None:
        """Release the device arrays (the object is unusable afterwards)."""
        if getattr(self, "_closed", True):
            return
        self._closed = True
        self._graph = None
        for name in ("_model", "_data", "_fields", "_parts", "_state_wp", "_active_wp", "_qpos", "_qvel", "_ctrl", "_act",
                     "_time", "_sens", "_warmstart", "_overflow", "_state_t", "_active_t"):
            if hasattr(self, name):
                setattr(self, name, None)

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
