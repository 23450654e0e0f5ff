"""The per-frame tracking errors a :class:`~adadex.envs.tracking.TrackingEnv` writes into every step.

They are the paper's metrics (Sec. 4.1) at one frame, defined here, at the env's level, so the env
never imports evaluation code; :mod:`adadex.eval.metrics` builds trajectory means and success
rates on them (and re-exports these names). :func:`frame_success` is the paper's per-frame success
test (:class:`Thresholds`): the frames completion success counts, and the reward's ``success`` term.
:func:`object_success` is the object-centric test reported beside it: the paper's test *and* the
object within ``Thresholds.object_position`` (5 cm) of its reference. The paper's test averages the
object and palm errors, so a frame with the palm on its reference passes with the object up to
~19 cm off (0.5·T_o + 0.5·T_h ≤ 10 cm): it cannot tell a hand that carries the object from one that
leaves it on the table; the object-centric test can.

``T_o`` object position error and ``T_h`` wrist (palm) position error in m, ``R_o`` and ``R_h``
their rotation errors in rad (angle of :func:`adadex.quat.quat_diff`, so q ≡ −q), ``E_finger`` the
mean absolute error of the 16 hand joints in rad.

Example
-------
>>> import numpy as np
>>> pose = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
>>> q = np.zeros(22)
>>> err = frame_errors(pose + [0.03, 0, 0, 0, 0, 0, 0], pose, pose, pose, q + 0.1, q)
>>> sorted(err) == sorted(ERROR_NAMES), round(float(err["T_o"]), 3), round(float(err["E_finger"]), 3)
(True, 0.03, 0.1)
>>> far = frame_errors(pose + [0.15, 0, 0, 0, 0, 0, 0], pose, pose, pose, q, q)    # object 15 cm off
>>> bool(frame_success(far)), bool(object_success(far)), bool(object_success(err))
(True, False, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from adadex.arrays import namespace
from adadex.errors import ConfigError
from adadex.quat import quat_angle_between
from adadex.sim.robot import ARM_JOINTS, NUM_JOINTS

ERROR_NAMES = ("T_o", "R_o", "T_h", "R_h", "E_finger")
_FINGERS = slice(len(ARM_JOINTS), NUM_JOINTS)


def frame_errors(object_pose: torch.Tensor, ref_object_pose: torch.Tensor, palm_pose: torch.Tensor,
                 ref_palm_pose: torch.Tensor, joint_pos: torch.Tensor, ref_joint_pos: torch.Tensor
                 ) -> dict[str, torch.Tensor]:
    """Per-frame errors from (…, 7) poses and (…, 22) joint positions (torch tensors or numpy
    arrays); each output has shape (…)."""
    norm = namespace(object_pose).linalg.vector_norm
    return {
        "T_o": norm(object_pose[..., :3] - ref_object_pose[..., :3], axis=-1),
        "R_o": quat_angle_between(object_pose[..., 3:], ref_object_pose[..., 3:]),
        "T_h": norm(palm_pose[..., :3] - ref_palm_pose[..., :3], axis=-1),
        "R_h": quat_angle_between(palm_pose[..., 3:], ref_palm_pose[..., 3:]),
        "E_finger": abs(joint_pos[..., _FINGERS] - ref_joint_pos[..., _FINGERS]).mean(axis=-1),
    }


@dataclass(frozen=True)
class Thresholds:
    """Success thresholds (SI units): positions and distances in m, rotations in rad.

    The paper's (Sec. 4.1): ``position`` bounds 0.5·T_o + 0.5·T_h, ``rotation`` 0.5·R_o + 0.5·R_h,
    ``finger`` E_finger (:func:`frame_success`).

    The object-centric ones reported beside them (not the paper's):

    * ``object_position`` (5 cm): bounds T_o alone in :func:`object_success` (a frame that meets the
      paper's thresholds with the object within 5 cm of its reference) and in ``carried``;
    * ``carry_motion`` (3 cm) and ``carry_fraction`` (0.8), the trajectory test ``carried``
      (:func:`adadex.eval.metrics.trajectory_metrics`): over the frames where the *reference* object
      is more than ``carry_motion`` from its start position, T_o ≤ ``object_position`` on at least
      ``carry_fraction`` of them (frames never reached count as failures); a trajectory whose
      reference object never moves that far is carried iff its object completion ≥ ``carry_fraction``;
    * ``lift`` (3 cm), the trajectory test ``lifted``: where the reference raises its object at least
      ``lift`` above its start, whether the object rose min(``lift``, half the reference's highest
      rise) on a frame the episode tracked — a hand that closed on it and raised it, whatever came after.

    Attributes:
        position: bound of 0.5·T_o + 0.5·T_h, m (default 0.10).
        rotation: bound of 0.5·R_o + 0.5·R_h, rad (default 60°).
        finger: bound of E_finger, rad (default 40°).
        object_position: bound of T_o alone, m (default 0.05).
        carry_motion: how far the reference object must be from its start for a frame to count
            in ``carried``, m (default 0.03).
        carry_fraction: the fraction of those frames that must hold T_o ≤ ``object_position``,
            in (0, 1] (default 0.8).
        lift: how far the reference must raise its object for ``lifted`` to apply, and the most the
            object must rise to count as lifted, m (default 0.03).

    Every field must be positive (:class:`~adadex.errors.ConfigError` otherwise).

    Examples:
        >>> Thresholds().position, round(math.degrees(Thresholds().rotation))
        (0.1, 60)
    """

    position: float = 0.10
    rotation: float = math.radians(60.0)
    finger: float = math.radians(40.0)
    object_position: float = 0.05
    carry_motion: float = 0.03
    carry_fraction: float = 0.8
    lift: float = 0.03

    def __post_init__(self):
        for k in ("position", "rotation", "finger", "object_position", "carry_motion", "carry_fraction", "lift"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"Thresholds.{k} must be a positive number, got {v}")
        if self.carry_fraction > 1:
            raise ConfigError(f"Thresholds.carry_fraction must be in (0, 1], got {self.carry_fraction}")


def frame_success(errors: dict, thresholds: Thresholds = Thresholds()):
    """Whether each frame meets the thresholds: 0.5·T_o + 0.5·T_h ≤ position,
    0.5·R_o + 0.5·R_h ≤ rotation and E_finger ≤ finger (bool, the errors' shape; torch or numpy).

    Args:
        errors: per-frame errors, at least ``"T_o"``, ``"T_h"`` (m), ``"R_o"``, ``"R_h"``,
            ``"E_finger"`` (rad), arrays or tensors of one shape.
        thresholds: the bounds (default :class:`Thresholds`, the paper's).

    Examples:
        >>> import numpy as np
        >>> e = {"T_o": np.array([0.02, 0.3]), "T_h": np.array([0.02, 0.02]),
        ...      "R_o": np.zeros(2), "R_h": np.zeros(2), "E_finger": np.zeros(2)}
        >>> frame_success(e)
        array([ True, False])
    """
    position, rotation, finger = frame_tests(errors, thresholds)
    return position & rotation & finger


def frame_tests(errors: dict, thresholds: Thresholds = Thresholds()) -> tuple:
    """The three tests :func:`frame_success` joins, each on its own (bool, the errors' shape; torch or
    numpy): ``(position, rotation, finger)`` — 0.5·T_o + 0.5·T_h ≤ position, 0.5·R_o + 0.5·R_h ≤
    rotation, E_finger ≤ finger. Which one a failing frame fails is where a tracker loses it
    (:func:`adadex.eval.metrics.trajectory_metrics`' ``lost_*``).

    Args:
        errors: per-frame errors, as for :func:`frame_success`.
        thresholds: the bounds (default :class:`Thresholds`, the paper's).

    Examples:
        >>> import numpy as np
        >>> e = {"T_o": np.array([0.02, 0.02]), "T_h": np.array([0.02, 0.02]),
        ...      "R_o": np.array([0.0, 3.0]), "R_h": np.zeros(2), "E_finger": np.zeros(2)}
        >>> [t.tolist() for t in frame_tests(e)]
        [[True, True], [True, False], [True, True]]
    """
    th = thresholds
    return (0.5 * errors["T_o"] + 0.5 * errors["T_h"] <= th.position,
            0.5 * errors["R_o"] + 0.5 * errors["R_h"] <= th.rotation, errors["E_finger"] <= th.finger)


def object_success(errors: dict, thresholds: Thresholds = Thresholds()):
    """The object-centric per-frame test: :func:`frame_success` and T_o ≤ ``object_position`` (bool,
    the errors' shape; torch or numpy). Not the paper's; reported beside it (module docstring).

    Args:
        errors: per-frame errors, as :func:`frame_success` takes them.
        thresholds: the bounds (default :class:`Thresholds`).
    """
    return frame_success(errors, thresholds) & (errors["T_o"] <= thresholds.object_position)
