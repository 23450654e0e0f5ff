"""Import human–object data you bring: hand keypoints + object poses in an ``.npz``, retargeted to
the robot on import.

File layout (``.npz``)::

    keypoints    (T, 21, 3) float   one hand's keypoints in MANO joint order (see
                                    :data:`adadex.data.human_hand.KEYPOINT_NAMES`), world frame, metres;
                 (T, H, 21, 3)      with H hands — rejected as not single-handed unless H == 1
    object_pose  (T, 7) float       object position + w-first unit quaternion, world frame
    fps          scalar (optional)  frame rate of the file; resampled to 12 Hz if different (default 12)
    object_name  str (optional)     an object of the registry (``adadex sim info``)
    instruction  str (optional)     what the motion does

The world frame is the robot's: base at the origin, table top at z = 0, the robot reaching along +x.
Keypoints are scaled about the wrist to the robot's hand size (``scale="auto"``) during
retargeting (with ``retargeter=Retargeter(contact=ObjectContact())`` also aware of the object:
:mod:`adadex.data.object_contact`); the result goes through the same feasibility filter as
synthesized data.

Example::

    from adadex.data.hoi_import import import_npz
    ref = import_npz("my_take.npz", object_name="mug_00", instruction="lift the mug")
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from adadex.data import feasibility
from adadex.data.reference import (
    Reference,
    ReferenceError,
    ReferenceShapeError,
    ReferenceValueError,
)
from adadex.data.retarget import Retargeter
from scipy.spatial.transform import Slerp

from adadex.geometry import quat, rotation
from adadex.sim.scene import CONTROL_HZ


class ImportRejected(ReferenceError):
    """The file is valid but the motion fails the feasibility filter; ``rejection`` says why."""

    def __init__(self, message: str, rejection: feasibility.Rejection):
        super().__init__(message)
        self.rejection = rejection


def resample(keypoints: np.ndarray, object_pose: np.ndarray, fps: float, target_fps: float = CONTROL_HZ):
    """Keypoints (linear) and object poses (linear + slerp) at ``target_fps``."""
    T = len(keypoints)
    t_in = np.arange(T) / fps
    t_out = np.arange(int(np.floor(t_in[-1] * target_fps)) + 1) / target_fps
    kp = np.stack([np.stack([np.interp(t_out, t_in, keypoints[:, j, k]) for k in range(3)], -1)
                   for j in range(keypoints.shape[1])], 1)
    pos = np.stack([np.interp(t_out, t_in, object_pose[:, k]) for k in range(3)], -1)
    rot = Slerp(t_in, rotation(object_pose[:, 3:]))(t_out)
    return kp, np.concatenate([pos, quat(rot)], axis=1)


def _field(data, key: str, path: Path, default=None):
    if key in data.files:
        v = data[key]
        return v.item() if v.ndim == 0 else v
    if default is None:
        raise ReferenceError(f"{path}: missing array {key!r} (found {sorted(data.files)})")
    return default


#: Plausible frame rates of an imported file, Hz (inclusive): outside them ``fps`` is not frames per
#: second (a period, a typo), and resampling would make absurdly many frames or almost none.
FPS_RANGE = (1.0, 10_000.0)


def _fps(data, path: Path) -> float:
    """The file's ``fps``: one finite number in :data:`FPS_RANGE` (default: the control rate)."""
    if "fps" not in data.files:
        return float(CONTROL_HZ)
    v = data["fps"]
    if v.ndim != 0 and v.size != 1:
        raise ReferenceError(f"{path}: fps: expected one number (frames per second), got an array of shape {v.shape}")
    try:
        fps = float(v.reshape(()).item()) if v.dtype.kind in "iuf" else float("nan")
    except (TypeError, ValueError):
        fps = float("nan")
    lo, hi = FPS_RANGE
    if not (np.isfinite(fps) and lo <= fps <= hi):
        raise ReferenceError(f"{path}: fps: expected a frame rate in [{lo:g}, {hi:g}] Hz, got {v.reshape(-1)[0].item()!r}")
    return fps


def import_npz(path, *, object_name: str | None = None, instruction: str | None = None, group_id: int = 0,
               scale: float | str = "auto", retargeter: Retargeter | None = None,
               config: feasibility.FeasibilityConfig = feasibility.FeasibilityConfig()) -> Reference:
    """Read, validate, resample, retarget and check one ``.npz`` (see the module docstring).

    Args:
        path: the ``.npz`` file: ``keypoints`` (T, 21, 3) or (T, 1, 21, 3) in m, ``object_pose``
            (T, 7), optionally ``fps``, ``object_name``, ``instruction``.
        object_name: the object, overriding the file's (required if the file has none).
        instruction: the instruction text, overriding the file's (default: the file's, else the
            file name's stem).
        group_id: the semantic group id of the reference (default 0).
        scale: multiplies keypoint offsets from the wrist; ``"auto"`` (default) fits the robot's
            hand length (see :meth:`~adadex.data.retarget.Retargeter.retarget`).
        retargeter: the retargeter to use (default: a plain :class:`Retargeter`).
        config: the feasibility check's settings.

    Returns:
        the :class:`Reference`, resampled to the control rate and named after the file.

    Raises:
        ReferenceError: (its subclasses) a malformed file.
        ImportRejected: the motion is not feasible for the robot.
    """
    path = Path(path)
    if path.is_dir():
        raise ReferenceError(f"{path}: a folder, expected an .npz file")
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("a single .npy array, not an .npz archive")
        with data:
            kp = np.asarray(_field(data, "keypoints", path), dtype=np.float64)
            obj = np.asarray(_field(data, "object_pose", path), dtype=np.float64)
            fps = _fps(data, path)
            object_name = object_name or str(_field(data, "object_name", path, ""))
            instruction = instruction or str(_field(data, "instruction", path, path.stem))
    except FileNotFoundError:
        raise
    except ReferenceError:
        raise
    except (OSError, ValueError, TypeError, EOFError, zipfile.BadZipFile) as e:
        # a truncated or corrupt archive fails on opening or only when a key is read
        raise ReferenceError(f"{path}: cannot read as .npz ({type(e).__name__}: {e})") from None
    if not object_name:
        raise ReferenceError(f"{path}: no object_name in the file; pass object_name=")
    if kp.ndim == 4:
        if kp.shape[1] != 1:
            raise ImportRejected(f"{path}: {kp.shape[1]} hands; references are single-handed",
                                 feasibility.Rejection("two_hands", None, f"{kp.shape[1]} hands in the file"))
        kp = kp[:, 0]
    if kp.ndim != 3 or kp.shape[1:] != (21, 3):
        raise ReferenceShapeError(f"{path}: keypoints: expected shape (T, 21, 3), got {kp.shape}")
    if len(kp) < 2:
        raise ReferenceShapeError(f"{path}: keypoints: {len(kp)} frame(s); a motion needs at least 2")
    if obj.shape != (len(kp), 7):
        raise ReferenceShapeError(f"{path}: object_pose: expected shape ({len(kp)}, 7), got {obj.shape}")
    for name, arr in (("keypoints", kp), ("object_pose", obj)):
        bad = np.argwhere(~np.isfinite(arr))
        if len(bad):
            raise ReferenceValueError(f"{path}: {name}: non-finite value at frame {bad[0][0]}")
    norms = np.linalg.norm(obj[:, 3:], axis=1)
    if np.abs(norms - 1).max() > 1e-3:
        t = int(np.argmax(np.abs(norms - 1)))
        raise ReferenceError(f"{path}: object_pose quaternion at frame {t} has norm {norms[t]:.4f}, expected 1")
    if abs(fps - CONTROL_HZ) > 1e-6:
        kp, obj = resample(kp, obj, fps)
    rt = retargeter or Retargeter()
    try:
        res = rt.retarget(kp, scale=scale, object_pose=obj, object_names=object_name)
    except ReferenceError:
        raise
    except ValueError as e:            # the retargeter's checks of its input: a degenerate hand (all at one point) …
        raise ReferenceError(f"{path}: keypoints: cannot be retargeted ({e})") from None
    ref = Reference.from_joint_positions(
        res.joint_pos, obj, object_name=object_name, instruction=instruction, group_id=group_id, fps=CONTROL_HZ,
        human_keypoints=kp, retarget_residual=res.residual, name=path.stem,
        meta={"source": str(path), "source_fps": fps, "retarget_scale": float(res.scale[0])})
    rej = feasibility.check(ref, retarget_palm_error=res.palm_error, retarget_tip_error=res.tip_error, config=config)
    if rej is not None:
        raise ImportRejected(f"{path}: rejected ({rej.reason}): {rej.detail}", rej)
    return ref

