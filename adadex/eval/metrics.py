"""The paper's tracking metrics (Sec. 4.1), per frame, per trajectory and over a set of trajectories.

Per frame (:func:`frame_errors`, defined at the env's level in :mod:`adadex.envs.frame_errors` and
re-exported here): ``T_o`` object position error and ``T_h`` wrist (palm) position error in m,
``R_o`` and ``R_h`` their rotation errors in rad (angle of :func:`adadex.quat.quat_diff`, so q ≡ −q),
``E_finger`` the mean absolute error of the 16 hand joints in rad.

Success, two ways (:class:`Thresholds`, the paper's values by default):

*mean-error*  a trajectory succeeds when its *mean* errors satisfy 0.5·T_o + 0.5·T_h ≤ 10 cm,
              0.5·R_o + 0.5·R_h ≤ 60° and E_finger ≤ 40° — and it was tracked to its end (an episode
              terminated early is not a success);
*completion*  per trajectory, the fraction of its frames meeting the same thresholds (frames it
              never reached count as failures), averaged over trajectories.

The paper's metrics are the headline. Beside them, object-centric measures (not the paper's; the
thresholds are :class:`Thresholds` fields) that tell a policy that carries the object from one that
leaves it on the table, which the paper's averaged position test cannot (it passes a frame with the
palm on its reference and the object up to ~19 cm off):

*object completion*  per trajectory, the fraction of its frames meeting :func:`object_success` (the
              paper's thresholds and T_o ≤ ``object_position`` = 5 cm), counted like completion;
*carried*     per trajectory (bool): over its *moving* frames — where the reference object is more
              than ``carry_motion`` = 3 cm from its start position — T_o ≤ ``object_position`` on at
              least ``carry_fraction`` = 80 % of them (frames never reached count as failures); a
              trajectory whose reference object never moves that far is carried iff its object
              completion ≥ ``carry_fraction``. It needs the reference object's distance from its
              start at each frame (``reference_motion``); without it ``carried`` is left out.

Why episodes end, where the inputs allow (not the paper's either): ``ended_palm`` — the episode ended
with the palm beyond the env's termination error (``palm_limit``): the arm did not follow the
reference, whatever the object did; ``ended_unstable`` — it ended because the world's physics went
unstable (NaN, a MuJoCo reset, the object flung past the env's speed bound), not because the object or the
palm went too far from the reference (it needs the env's per-step ``unstable`` flag); ``lifted`` — of the trajectories whose reference raises the
object at least ``Thresholds.lift`` (``reference_lifts``), whether the object rose min(``lift``,
half that rise) above its start on a tracked frame: a hand that closed on the object and raised it
(it needs the object's and the reference's heights above their starts, ``object_rise`` and
``reference_rise``). Together with ``ended_early`` they say whether a failed episode never held its
object, held it and lost it, or lost the reference's arm path.

:func:`from_rollout` reads the per-frame errors a tracking environment writes into each step's
output (``("next", "privileged", "errors", name)``) from a TorchRL rollout of batch shape ``[B, T]``, so
evaluation never recomputes physics. Each row is one trajectory, up to and including its first
``done``; a row without frames is reported as empty and left out.

Example
-------
>>> import torch
>>> err = {k: torch.zeros(2, 3) for k in ERROR_NAMES}
>>> err["T_o"][1] = 0.5                                  # trajectory 1: object 50 cm off
>>> m = trajectory_metrics(err)
>>> m["success_mean_error"].tolist(), m["completion"].tolist()
([True, False], [1.0, 0.0])
>>> err["T_o"][1] = 0.15                                 # 15 cm: the paper's test passes, the object's fails
>>> m = trajectory_metrics(err, reference_motion=torch.tensor([[0.0, 0.05, 0.1]] * 2))
>>> m["completion"].tolist(), m["object_completion"].tolist(), m["carried"].tolist()
([1.0, 1.0], [1.0, 0.0], [True, False])
"""

from __future__ import annotations

import math

import torch

from adadex.envs.frame_errors import ERROR_NAMES, Thresholds, frame_errors, frame_success, frame_tests, object_success
from adadex.errors import ArrayError, UnknownKeyError

__all__ = ["ERROR_NAMES", "LOST", "Thresholds", "frame_errors", "frame_success", "frame_tests", "from_rollout",
           "object_rise_from_rollout", "object_success", "reference_motion_from_rollout", "summarize",
           "trajectory_metrics"]

#: where a trajectory's failing frames go (:func:`trajectory_metrics`), in the order a frame is charged: the
#: position test, else the rotation test, else the finger test, else never tracked (after an early end)
LOST = ("lost_position", "lost_rotation", "lost_finger", "lost_after_end")


def _check(errors: dict) -> tuple[int, int]:
    missing = [k for k in ERROR_NAMES if k not in errors]
    if missing:
        raise UnknownKeyError(f"errors lack {missing}; expected {ERROR_NAMES}")
    shapes = {k: tuple(errors[k].shape) for k in ERROR_NAMES}
    if len(set(shapes.values())) != 1 or len(next(iter(shapes.values()))) != 2:
        raise ArrayError(f"errors must all have shape (B, T); got {shapes}")
    return next(iter(shapes.values()))


def trajectory_metrics(errors: dict[str, torch.Tensor], valid: torch.Tensor | None = None,
                       lengths: torch.Tensor | None = None,
                       thresholds: Thresholds = Thresholds(),
                       reference_motion: torch.Tensor | None = None, palm_limit: float | None = None,
                       object_rise: torch.Tensor | None = None,
                       reference_rise: torch.Tensor | None = None,
                       unstable: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Per-trajectory means and both success measures from (B, T) per-frame errors.

    Args:
        errors: ``{name: (B, T) tensor}`` per-frame errors for each of ``ERROR_NAMES`` (``T_o``,
            ``T_h`` in m; ``R_o``, ``R_h``, ``E_finger`` in rad).
        valid: (B, T) bool, the frames each trajectory actually tracked (default: all).
        lengths: (B,) frames each trajectory should have tracked (default: its valid frames); a
            trajectory with fewer valid frames ended early.
        reference_motion: (B, T) the reference object's distance from its start position at each
            frame, in m (valid or not: it is the reference's); needed for ``carried``.
        thresholds: the success thresholds (default :class:`~adadex.envs.frame_errors.Thresholds`).
        palm_limit: the env's palm termination error (m, ``TrackingConfig.terminate_palm_error``);
            with it ``ended_palm``: ended early with T_h beyond it at the last tracked frame.
        object_rise, reference_rise: (B, T) the object's and the reference object's heights above
            their start positions at each frame, m (both or neither); with them ``reference_lifts``
            and ``lifted`` (the module docstring).
        unstable: (B, T) bool, the env's flag that the world's physics went unstable at that step
            (``("next", "privileged", "unstable")``); with it ``ended_unstable``: ended early with the flag
            set at the last tracked frame.

    Returns (B,) tensors: the mean of each error (NaN for an empty trajectory), ``frames``,
    ``ended_early``, ``success_mean_error`` (bool), ``completion`` (fraction), ``empty`` (bool),
    ``object_completion`` (fraction), where the other frames were lost (:data:`LOST`, fractions of the
    frames it should have tracked, summing with ``completion`` to 1: ``lost_position`` — tracked, failing
    the position test; ``lost_rotation`` — passing it, failing the rotation test; ``lost_finger`` —
    failing only the finger test; ``lost_after_end`` — never tracked, the episode having ended) and,
    with ``reference_motion``, ``carried`` (bool) and ``moving_frames`` (how many frames the carry test
    looked at; 0: it used object completion); with ``palm_limit``, ``ended_palm`` (bool); with
    ``unstable``, ``ended_unstable`` (bool); with the rises,
    ``reference_lifts`` and ``lifted`` (bool; ``lifted`` only where the reference lifts).
    """
    B, T = _check(errors)
    valid = torch.ones(B, T, dtype=torch.bool) if valid is None else valid.to(torch.bool)
    n = valid.sum(1)
    target = n if lengths is None else torch.as_tensor(lengths).to(n.dtype)
    if (target < n).any():
        raise ArrayError("lengths must be at least the number of valid frames of each trajectory")
    out: dict[str, torch.Tensor] = {}
    for k in ERROR_NAMES:
        e = torch.where(valid, errors[k].to(torch.float64), 0.0)
        out[k] = torch.where(n > 0, e.sum(1) / n.clamp(min=1), torch.nan)
    good = frame_success(errors, thresholds) & valid
    out["frames"] = n
    out["empty"] = n == 0
    out["ended_early"] = n < target
    out["success_mean_error"] = (~out["empty"]) & (~out["ended_early"]) & frame_success(out, thresholds)
    out["completion"] = torch.where(target > 0, good.sum(1) / target.clamp(min=1), 0.0).to(torch.float64)
    position, rotation, finger = frame_tests(errors, thresholds)
    charged = (valid & ~position, valid & position & ~rotation, valid & position & rotation & ~finger)
    for name, frames in zip(LOST, (*(c.sum(1) for c in charged), target - n)):
        out[name] = torch.where(target > 0, frames.to(torch.float64) / target.clamp(min=1), 0.0)
    held = object_success(errors, thresholds) & valid
    out["object_completion"] = torch.where(target > 0, held.sum(1).to(torch.float64) / target.clamp(min=1), 0.0)
    if reference_motion is not None:
        motion = torch.as_tensor(reference_motion)
        if tuple(motion.shape) != (B, T):
            raise ArrayError(f"reference_motion must have the errors' shape {(B, T)}, got {tuple(motion.shape)}")
        moving = motion > thresholds.carry_motion
        near = valid & (errors["T_o"] <= thresholds.object_position)
        m = moving.sum(1)
        followed = (moving & near).sum(1)
        carried = torch.where(m > 0, followed >= thresholds.carry_fraction * m,
                              out["object_completion"] >= thresholds.carry_fraction)
        out["carried"] = carried & ~out["empty"]
        out["moving_frames"] = m
    if palm_limit is not None:
        frame = torch.arange(T, device=valid.device).expand(B, T)
        last = torch.where(valid, frame, -1).max(1).values.clamp(min=0)          # the last tracked frame
        palm_end = errors["T_h"].gather(1, last[:, None])[:, 0] > palm_limit
        out["ended_palm"] = out["ended_early"] & ~out["empty"] & palm_end
    if unstable is not None:
        flag = torch.as_tensor(unstable).to(torch.bool)
        if tuple(flag.shape) != (B, T):
            raise ArrayError(f"unstable must have the errors' shape {(B, T)}, got {tuple(flag.shape)}")
        frame = torch.arange(T, device=valid.device).expand(B, T)
        last = torch.where(valid, frame, -1).max(1).values.clamp(min=0)
        out["ended_unstable"] = out["ended_early"] & ~out["empty"] & flag.gather(1, last[:, None])[:, 0]
    if (object_rise is None) != (reference_rise is None):
        raise ArrayError("object_rise and reference_rise go together: give both or neither")
    if object_rise is not None:
        rises = [torch.as_tensor(r).to(torch.float64) for r in (object_rise, reference_rise)]
        if any(tuple(r.shape) != (B, T) for r in rises):
            raise ArrayError(f"object_rise and reference_rise must have the errors' shape {(B, T)}, "
                             f"got {[tuple(r.shape) for r in rises]}")
        top = rises[1].max(1).values
        out["reference_lifts"] = top >= thresholds.lift
        need = torch.minimum(torch.full_like(top, thresholds.lift), 0.5 * top)
        out["lifted"] = out["reference_lifts"] & (valid & (rises[0] >= need[:, None])).any(1)
    return out


#: the unit of each error mean in a summary (and in the training logs): positions in cm, rotations and
#: fingers in rad — the paper's tables' units
SUMMARY_UNITS = {"T_o": "cm", "T_h": "cm", "R_o": "rad", "R_h": "rad", "E_finger": "rad"}
#: the factor from a frame error (:data:`ERROR_NAMES`, m and rad) to its summary unit
SUMMARY_SCALE = {k: 100.0 if u == "cm" else 1.0 for k, u in SUMMARY_UNITS.items()}


def with_units(values: dict, prefix: str = "") -> dict:
    """``values`` with each error mean named with its unit (``T_o`` → ``T_o_cm``; the other names, whose
    unit is in the name already or that have none, as they are), each key prefixed with ``prefix``:
    the names of the training logs (``metrics.csv``, wandb).

    Args:
        values: a summary (:func:`summarize`) or any dict keyed by metric names.
        prefix: put before every key (default ``""``).

    Examples:
        >>> with_units({"T_o": 9.8, "R_h": 0.1, "completion_pct": 82.0}, "eval_")
        {'eval_T_o_cm': 9.8, 'eval_R_h_rad': 0.1, 'eval_completion_pct': 82.0}
    """
    return {f"{prefix}{k}_{SUMMARY_UNITS[k]}" if k in SUMMARY_UNITS else f"{prefix}{k}": v for k, v in values.items()}


def summarize(per_traj: dict[str, torch.Tensor]) -> dict[str, float]:
    """Over non-empty trajectories: mean errors (positions in cm, rotations in rad, fingers in rad)
    and success rates in %, as the paper's tables report them.

    Args:
        per_traj: a :func:`trajectory_metrics` (or :func:`from_rollout`) result.

    Returns:
        ``{"trajectories", "empty"}`` (counts), the mean of each error (``T_o``, ``T_h`` in cm;
        ``R_o``, ``R_h``, ``E_finger`` in rad) and ``success_mean_error_pct``, ``completion_pct``,
        ``object_completion_pct``, ``carried_pct`` (NaN without ``carried``) and, where the result
        has them, the lost frames (:data:`LOST`) as ``lost_position_pct`` …, ``ended_pct`` (episodes
        that ended early), ``ended_palm_pct`` (of all episodes, those that ended with the palm beyond
        the termination error), ``ended_unstable_pct`` (of all episodes, those that ended with the physics
        unstable) and ``lifted_pct`` (of the episodes whose reference lifts its object,
        those that raised it; NaN when none does); every mean is NaN when no trajectory is non-empty.
    """
    keep = ~per_traj["empty"]
    n = int(keep.sum())
    out = {"trajectories": n, "empty": int(per_traj["empty"].sum())}
    if n == 0:
        return out | {k: math.nan for k in (*ERROR_NAMES, "success_mean_error_pct", "completion_pct",
                                            "object_completion_pct", "carried_pct")}
    for k in ERROR_NAMES:
        out[k] = float(per_traj[k][keep].mean()) * SUMMARY_SCALE[k]
    out["success_mean_error_pct"] = 100.0 * float(per_traj["success_mean_error"][keep].double().mean())
    out["completion_pct"] = 100.0 * float(per_traj["completion"][keep].mean())
    out["object_completion_pct"] = 100.0 * float(per_traj["object_completion"][keep].mean())
    out["carried_pct"] = (100.0 * float(per_traj["carried"][keep].double().mean()) if "carried" in per_traj
                          else math.nan)
    out.update({f"{k}_pct": 100.0 * float(per_traj[k][keep].mean()) for k in LOST if k in per_traj})
    out["ended_pct"] = 100.0 * float(per_traj["ended_early"][keep].double().mean())
    if "ended_palm" in per_traj:
        out["ended_palm_pct"] = 100.0 * float(per_traj["ended_palm"][keep].double().mean())
    if "ended_unstable" in per_traj:
        out["ended_unstable_pct"] = 100.0 * float(per_traj["ended_unstable"][keep].double().mean())
    if "lifted" in per_traj:
        lifts = keep & per_traj["reference_lifts"]
        out["lifted_pct"] = 100.0 * float(per_traj["lifted"][lifts].double().mean()) if lifts.any() else math.nan
    return out


#: what :func:`reference_motion_from_rollout` reads: the current reference frame (offset 0 of the
#: env's reference window) and the reference object's pose at the episode's first frame
REF_OBJECT_POSE_KEY = ("next", "reference", "object_pose")
REF_OBJECT_START_KEY = ("next", "object", "reference_start")
#: the env's flag that a world's physics went unstable at a step (``ended_unstable``)
UNSTABLE_KEY = ("next", "privileged", "unstable")


def _reference_offset(td) -> torch.Tensor | None:
    """(…, T, 3) the reference object's position minus its start, from a tracking env's rollout; None
    where :func:`reference_motion_from_rollout` says."""
    keys = set(td.keys(include_nested=True))
    if REF_OBJECT_POSE_KEY not in keys or REF_OBJECT_START_KEY not in keys or ("next", "modulation") in keys \
            or "modulation" in keys:
        return None
    return td.get(REF_OBJECT_POSE_KEY)[..., 0, :3].to(torch.float64) - \
        td.get(REF_OBJECT_START_KEY)[..., :3].to(torch.float64)


def reference_motion_from_rollout(td) -> torch.Tensor | None:
    """(…, T) the reference object's distance from its start position at each frame of a tracking
    env's rollout (``[…, T]``), from the entries the env writes: ``("next", "reference",
    "object_pose")`` at offset 0 against ``("next", "object", "reference_start")``; ``None`` when
    the rollout lacks them or holds a modulation (channel R shows the *edited* reference in those
    entries, so the original's motion must come from the dataset, as
    :func:`adadex.eval.evaluate.evaluate` does)."""
    offset = _reference_offset(td)
    return None if offset is None else torch.linalg.vector_norm(offset, dim=-1)


#: what :func:`object_rise_from_rollout` reads: the object's pose after each step and where it started
OBJECT_POSE_KEY = ("next", "object", "pose")
OBJECT_START_KEY = ("next", "object", "start_pose")


def object_rise_from_rollout(td) -> torch.Tensor | None:
    """(…, T) the object's height above where it started the episode at each frame of a tracking env's
    rollout (``("next", "object", "pose")`` against ``("next", "object", "start_pose")``), m; ``None``
    when the rollout lacks them."""
    keys = set(td.keys(include_nested=True))
    if OBJECT_POSE_KEY not in keys or OBJECT_START_KEY not in keys:
        return None
    return td.get(OBJECT_POSE_KEY)[..., 2].to(torch.float64) - td.get(OBJECT_START_KEY)[..., 2].to(torch.float64)


def from_rollout(td, *, errors_key=("next", "privileged", "errors"), lengths: torch.Tensor | None = None,
                 thresholds: Thresholds = Thresholds(), reference_motion: torch.Tensor | None = None,
                 palm_limit: float | None = None,
                 reference_rise: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """:func:`trajectory_metrics` of a TorchRL rollout TensorDict of batch shape ``[..., T]`` (time
    last): ``[B, T]`` from one env, ``[workers, B, T]`` from a multi-process collector, … — every
    leading index is one trajectory, in row-major order.

    A trajectory's frames run up to and including its first ``("next", "done")``; frames after
    it (an auto-reset next episode) are not counted.

    ``reference_motion`` (the rollout's batch shape, m) is what ``carried`` needs; by default it is
    read from the rollout (:func:`reference_motion_from_rollout`), and ``carried`` is left out
    where that is not possible. ``lifted`` needs the object's rise, read from the rollout
    (:func:`object_rise_from_rollout`), and the reference's (``reference_rise``, by default from the
    rollout's reference entries as for the motion, over the frames up to each episode's end, so an
    episode that ended before its reference lifts does not count as one whose reference lifts; pass the
    whole window's, as :func:`adadex.eval.evaluate.evaluate` does from the dataset); it is left out where
    either is missing. ``ended_unstable`` is read from the env's ``("next", "privileged", "unstable")`` flag
    where the rollout holds it.

    Args:
        td: the rollout, batch shape ``[..., T]``, holding ``("next", "done")`` and the errors.
        errors_key: where the per-frame errors are (default ``("next", "privileged", "errors")``).
        lengths: frames each trajectory should have tracked (see :func:`trajectory_metrics`).
        thresholds: the success thresholds.
        reference_motion: the reference object's distance from its start, m, or None (above).
        palm_limit: the env's palm termination error, m (``ended_palm``; see :func:`trajectory_metrics`).
        reference_rise: the reference object's height above its start, m, or None (above).

    Returns:
        :func:`trajectory_metrics`'s (B,) tensors, B the product of the leading dimensions.
    """
    if td.batch_dims < 2:
        raise ArrayError(f"expected a rollout of batch shape [..., T] with time last, got {list(td.batch_size)}")
    if td.batch_dims > 2:
        td = td.reshape(-1, td.batch_size[-1])
    errs = td.get(errors_key)
    errors = {k: errs.get(k).reshape(td.batch_size) for k in ERROR_NAMES}
    done = td.get(("next", "done")).reshape(td.batch_size).to(torch.bool)
    after_done = torch.cumsum(done.int(), dim=1) - done.int() > 0
    motion = reference_motion_from_rollout(td) if reference_motion is None else torch.as_tensor(reference_motion)
    if motion is not None:
        motion = motion.reshape(td.batch_size)
    if reference_rise is None:         # read from the rollout: up to each episode's end (an auto-reset follows)
        offset = _reference_offset(td)
        reference_rise = None if offset is None else \
            torch.where(after_done, -math.inf, offset[..., 2].reshape(td.batch_size))
    rise = object_rise_from_rollout(td)
    rises = {}
    if rise is not None and reference_rise is not None:
        rises = {"object_rise": rise.reshape(td.batch_size),
                 "reference_rise": torch.as_tensor(reference_rise).reshape(td.batch_size)}
    flag = td.get(UNSTABLE_KEY, None)
    unstable = None if flag is None else flag.reshape(td.batch_size)
    return trajectory_metrics(errors, valid=~after_done, lengths=lengths, thresholds=thresholds,
                              reference_motion=motion, palm_limit=palm_limit, unstable=unstable, **rises)
