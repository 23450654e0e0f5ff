"""Hand–object references: the time-indexed targets the tracker follows, and datasets of them.

A :class:`Reference` holds, per frame (``fps`` frames per second; adadex uses one frame per control
step, 12 Hz):

``hand_joint_pos`` (T, 22)
    robot joint positions in :data:`~adadex.sim.robot.JOINT_NAMES` order (rad);
``hand_link_pose`` (T, 5, 7)
    poses of the tracked links (:data:`~adadex.sim.robot.TRACKED_SITES`: palm + 4 fingertips) in the
    world frame, position (m) + w-first unit quaternion; the forward kinematics of ``hand_joint_pos``;
``object_pose`` (T, 7)
    the object's pose in the world frame;

plus the object name, the instruction text, the semantic group id (a base instruction and its
paraphrases share one), and optionally the human keypoints (T, 21, 3) it was retargeted from and
the per-frame retargeting residual.

An episode tracks :data:`WINDOW_FRAMES` frames starting at :meth:`Reference.window_start`, the
first frame where the palm is more than :data:`WINDOW_START_DISTANCE` from the object centre.

A dataset on disk is a folder::

    index.json     one entry per reference: frame offset and length, object, instruction, group …
    splits.json    named splits (unseen_trajectory, unseen_object), each {"train": [...], "test": [...]}
    frames/        a tensordict memmap of every frame of every reference, concatenated

:func:`save_dataset` writes the whole folder next to the target and renames it into place;
:class:`ReferenceDataset` reads ``index.json`` and maps the frames lazily, so opening a large
dataset costs milliseconds and a reference is read only when indexed.

Example
-------
>>> import tempfile, numpy as np
>>> from adadex.data.reference import Reference, ReferenceDataset, save_dataset
>>> T = 320
>>> q = np.zeros((T, 22)); q[:, 1] = -0.35
>>> ref = Reference.from_joint_positions(q, np.tile([0.45, 0, 0.03, 1, 0, 0, 0], (T, 1)),
...                                      object_name="cube_050", instruction="hold still", group_id=0)
>>> folder = save_dataset([ref], tempfile.mkdtemp() + "/ds")
>>> ds = ReferenceDataset(folder)
>>> len(ds), ds[0].instruction, ds[0].hand_link_pose.shape
(1, 'hold still', (320, 5, 7))
"""

from __future__ import annotations

import json
import numbers
import operator
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from adadex.errors import AdadexError
from adadex.io import OutputExistsError, atomic_write_text, json_default, output_folder
from adadex.sim.objects import REGISTRY, UnknownObjectError
from adadex.sim.robot import JOINT_NAMES, NUM_JOINTS, TRACKED_SITES, joint_limits
from adadex.sim.scene import CONTROL_HZ

#: Frames an episode tracks (paper: 300).
WINDOW_FRAMES = 300
#: An episode starts at the first frame where the palm is farther than this from the object centre (m).
WINDOW_START_DISTANCE = 0.20
#: Joint positions may exceed their limits by this much (rad) before a reference is rejected.
JOINT_LIMIT_TOLERANCE = 0.02
#: Largest accepted deviation of a quaternion's norm from 1.
QUAT_NORM_TOLERANCE = 1e-3
NUM_KEYPOINTS = 21
FORMAT_VERSION = 1

_FRAME_FIELDS = ("hand_joint_pos", "hand_link_pose", "object_pose", "human_keypoints", "retarget_residual")


class ReferenceError(AdadexError, ValueError):
    """Invalid reference data; the message says what is wrong and where."""


class ReferenceShapeError(ReferenceError):
    """An array has the wrong shape (expected vs got)."""


class ReferenceValueError(ReferenceError):
    """NaN or ±inf in an array."""


class QuaternionNormError(ReferenceError):
    """A quaternion is not of unit norm."""


class JointLimitError(ReferenceError):
    """A joint position lies outside its limits by more than the tolerance."""


class ReferenceObjectError(ReferenceError, UnknownObjectError):
    """The object is not in the registry (also an ``objects.UnknownObjectError``)."""

    def __init__(self, message: str):
        Exception.__init__(self, message)

    def __str__(self) -> str:
        return str(self.args[0])


class WindowTooShortError(ReferenceError):
    """Fewer than :data:`WINDOW_FRAMES` frames follow the episode start."""


class DatasetError(ReferenceError):
    """A folder that is not a readable reference dataset, or an inconsistent one."""


class ReferenceIndexError(DatasetError, IndexError):
    """A reference index outside the dataset (also an ``IndexError``, as a sequence's)."""


class SplitError(DatasetError, KeyError):
    """A split or part the dataset does not have (also a ``KeyError``)."""

    def __str__(self) -> str:
        return str(self.args[0])


def _array(value, name: str, shape_tail: tuple[int, ...], where: str) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ReferenceError(f"{where}: {name}: cannot convert to a float array ({e})") from None
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        want = "(T, " + ", ".join(map(str, shape_tail)) + ")" if shape_tail else "(T,)"
        raise ReferenceShapeError(f"{where}: {name}: expected shape {want}, got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        idx = np.argwhere(bad)[0]
        raise ReferenceValueError(f"{where}: {name}: non-finite value {arr[tuple(idx)]} at frame {idx[0]}"
                                  f" (index {tuple(int(i) for i in idx)})")
    arr.setflags(write=False)
    return arr


def _check_quats(q: np.ndarray, name: str, where: str) -> None:
    err = np.abs(np.linalg.norm(q, axis=-1) - 1.0)
    if (err > QUAT_NORM_TOLERANCE).any():
        idx = np.unravel_index(int(np.argmax(err)), err.shape)
        raise QuaternionNormError(f"{where}: {name}: quaternion at frame {idx[0]} (index {tuple(map(int, idx))})"
                                  f" has norm {np.linalg.norm(q[idx]):.6f}, expected 1 ± {QUAT_NORM_TOLERANCE}")


@dataclass(frozen=True, eq=False)
class Reference:
    """One hand–object reference; building it validates every field (see the module docstring).

    Use :meth:`from_joint_positions` to fill ``hand_link_pose`` by forward kinematics.

    Attributes:
        hand_joint_pos: (T, 22) robot joint positions in ``JOINT_NAMES`` order, rad; within the
            joint limits (up to ``JOINT_LIMIT_TOLERANCE``).
        hand_link_pose: (T, 5, 7) world poses of the palm and the 4 fingertips: position (m) +
            w-first unit quaternion.
        object_pose: (T, 7) the object's world pose, position (m) + w-first unit quaternion.
        object_name: the object, a name of :data:`~adadex.sim.objects.REGISTRY`.
        instruction: the instruction text.
        group_id: the semantic group (a base instruction and its paraphrases share one).
        fps: frames per second (default ``CONTROL_HZ``, one frame per control step).
        human_keypoints: optional (T, 21, 3) human hand keypoints it was retargeted from, m.
        retarget_residual: optional (T,) per-frame retargeting residual.
        meta: JSON-serializable provenance (verb, parameters, paraphrase index, seed …).
        name: the reference's name in a dataset (default "": unnamed; :func:`save_dataset` names it by
            its index).
    """

    hand_joint_pos: np.ndarray
    hand_link_pose: np.ndarray
    object_pose: np.ndarray
    object_name: str
    instruction: str
    group_id: int
    fps: float = CONTROL_HZ
    human_keypoints: np.ndarray | None = None
    retarget_residual: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    name: str = ""

    def __post_init__(self):
        where = f"reference {self.name!r}" if self.name else "reference"
        put = object.__setattr__
        put(self, "hand_joint_pos", _array(self.hand_joint_pos, "hand_joint_pos", (NUM_JOINTS,), where))
        T = len(self.hand_joint_pos)
        put(self, "hand_link_pose", _array(self.hand_link_pose, "hand_link_pose", (len(TRACKED_SITES), 7), where))
        put(self, "object_pose", _array(self.object_pose, "object_pose", (7,), where))
        for name in ("human_keypoints", "retarget_residual"):
            value = getattr(self, name)
            if value is not None:
                tail = (NUM_KEYPOINTS, 3) if name == "human_keypoints" else ()
                put(self, name, _array(value, name, tail, where))
        for name in ("hand_link_pose", "object_pose", "human_keypoints", "retarget_residual"):
            value = getattr(self, name)
            if value is not None and len(value) != T:
                raise ReferenceShapeError(f"{where}: {name} has {len(value)} frames, hand_joint_pos has {T}")
        _check_quats(self.hand_link_pose[..., 3:], "hand_link_pose", where)
        _check_quats(self.object_pose[:, 3:], "object_pose", where)
        if self.object_name not in REGISTRY:
            raise ReferenceObjectError(f"{where}: unknown object {self.object_name!r} "
                                       f"(see `adadex sim info` for the {len(REGISTRY)} known objects)")
        if not (isinstance(self.fps, numbers.Real) and np.isfinite(self.fps) and self.fps > 0):
            raise ReferenceError(f"{where}: fps must be a positive number, got {self.fps}")
        put(self, "group_id", int(self.group_id))
        lim = joint_limits()
        over = np.maximum(lim[:, 0] - self.hand_joint_pos, self.hand_joint_pos - lim[:, 1])
        if (over > JOINT_LIMIT_TOLERANCE).any():
            t, j = np.unravel_index(int(np.argmax(over)), over.shape)
            raise JointLimitError(
                f"{where}: joint {JOINT_NAMES[j]} at frame {t} is {self.hand_joint_pos[t, j]:+.4f} rad, outside "
                f"[{lim[j, 0]:+.4f}, {lim[j, 1]:+.4f}] by {over[t, j]:.4f} (tolerance {JOINT_LIMIT_TOLERANCE})")

    @classmethod
    def from_joint_positions(cls, hand_joint_pos, object_pose, **kwargs) -> Reference:
        """A reference whose tracked-link poses are the forward kinematics of ``hand_joint_pos``."""
        import torch  # forward kinematics is torch code; plain data users never get here

        q = np.asarray(hand_joint_pos, dtype=np.float64)
        if q.ndim == 2 and q.shape[-1] == NUM_JOINTS:
            poses = _fk().link_poses(torch.as_tensor(q)).numpy()
        else:  # let validation report the shape
            poses = np.zeros((len(q), len(TRACKED_SITES), 7))
        return cls(hand_joint_pos=hand_joint_pos, hand_link_pose=poses, object_pose=object_pose, **kwargs)

    @property
    def num_frames(self) -> int:
        return len(self.hand_joint_pos)

    @property
    def duration(self) -> float:
        return self.num_frames / self.fps

    def palm_object_distance(self) -> np.ndarray:
        """(T,) distance from the palm to the object centre, m."""
        return np.linalg.norm(self.hand_link_pose[:, 0, :3] - self.object_pose[:, :3], axis=-1)

    def window_start(self, distance: float = WINDOW_START_DISTANCE) -> int:
        """First frame where the palm is farther than ``distance`` from the object centre.

        Raises :class:`WindowTooShortError` if no frame qualifies.
        """
        far = np.flatnonzero(self.palm_object_distance() > distance)
        if far.size == 0:
            raise WindowTooShortError(f"reference {self.name!r}: the palm never gets farther than "
                                      f"{distance} m from the object, so no episode can start")
        return int(far[0])

    def window(self, frames: int = WINDOW_FRAMES, distance: float = WINDOW_START_DISTANCE) -> slice:
        """The episode's frames: ``frames`` frames from :meth:`window_start`.

        Raises :class:`WindowTooShortError` when fewer frames follow the start.
        """
        start = self.window_start(distance)
        if start + frames > self.num_frames:
            raise WindowTooShortError(
                f"reference {self.name!r}: {self.num_frames} frames, the episode starts at frame {start} and "
                f"needs {frames} frames, so {start + frames - self.num_frames} are missing")
        return slice(start, start + frames)

    def validate(self, frames: int = WINDOW_FRAMES) -> Reference:
        """Full check including the episode window; returns ``self``."""
        self.window(frames)
        return self

    def with_name(self, name: str) -> Reference:
        return replace(self, name=name)


_FK = None


def _fk():
    global _FK
    if _FK is None:
        from adadex.sim.kinematics import RobotKinematics

        _FK = RobotKinematics()
    return _FK


# ----------------------------------------------------------------------------------------------
# Datasets on disk


def _frames_tensordict(refs: Sequence[Reference]):
    import torch
    from tensordict import TensorDict

    def cat(name, tail, fill=0.0):
        parts = []
        for r in refs:
            v = getattr(r, name)
            parts.append(np.full((r.num_frames, *tail), fill) if v is None else v)
        return torch.as_tensor(np.concatenate(parts).astype(np.float32))

    n = sum(r.num_frames for r in refs)
    return TensorDict({
        "hand_joint_pos": cat("hand_joint_pos", (NUM_JOINTS,)),
        "hand_link_pose": cat("hand_link_pose", (len(TRACKED_SITES), 7)),
        "object_pose": cat("object_pose", (7,)),
        "human_keypoints": cat("human_keypoints", (NUM_KEYPOINTS, 3)),
        "retarget_residual": cat("retarget_residual", (), fill=np.nan),
    }, batch_size=[n])


def _index_entry(ref: Reference, offset: int, i: int) -> dict:
    try:
        start = ref.window_start()
    except WindowTooShortError:
        start = None
    return {
        "name": ref.name or f"ref{i:05d}", "offset": offset, "length": ref.num_frames, "fps": ref.fps,
        "object": ref.object_name, "instruction": ref.instruction, "group": ref.group_id,
        "window_start": start, "has_keypoints": ref.human_keypoints is not None,
        "has_residual": ref.retarget_residual is not None, "meta": ref.meta,
    }


def check_splits(splits: dict, n: int) -> dict:
    """Validate named splits ``{name: {part: [indices]}}`` over ``n`` references; returns them as lists."""
    if not isinstance(splits, dict):
        raise DatasetError(f"splits: expected {{name: {{part: [indices]}}}}, got {type(splits).__name__}")
    out = {}
    for name, parts in splits.items():
        if not isinstance(parts, dict):
            raise DatasetError(f"split {name!r}: expected {{part: [indices]}}, got {type(parts).__name__}")
        seen: dict[int, str] = {}
        out[name] = {}
        for part, idx in parts.items():
            try:
                if isinstance(idx, (str, bytes, dict)):
                    raise TypeError
                idx = list(idx)
            except TypeError:
                raise DatasetError(f"split {name!r}/{part}: expected a list of indices, "
                                   f"got {type(idx).__name__}") from None
            for k, i in enumerate(idx):
                try:
                    idx[k] = i = operator.index(i)
                except TypeError:
                    raise DatasetError(f"split {name!r}/{part}: index {i!r} is not an integer") from None
                if not 0 <= i < n:
                    raise DatasetError(f"split {name!r}/{part}: index {i} outside 0..{n - 1}")
                if seen.get(i) == part:
                    raise DatasetError(f"split {name!r}/{part}: reference {i} appears twice")
                if i in seen:
                    raise DatasetError(f"split {name!r}: reference {i} is in both {seen[i]!r} and {part!r}")
                seen[i] = part
            out[name][part] = idx
    return out


def is_dataset(path) -> bool:
    """True if ``path`` is a folder holding an adadex reference dataset (its ``index.json``).

    Args:
        path: any path; a missing or unreadable one is not a dataset.

    Examples:
        >>> import tempfile
        >>> is_dataset(tempfile.mkdtemp())
        False
    """
    path = Path(path)
    try:
        index = json.loads((path / "index.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(index, dict) and "version" in index and "references" in index and (path / "frames").is_dir()


def save_dataset(refs: Sequence[Reference], path, *, splits: dict | None = None,
                 info: dict | None = None, overwrite: bool = True, force: bool = False) -> Path:
    """Write ``refs`` as a dataset folder at ``path``, atomically (see the module docstring).

    The folder is built beside ``path`` and renamed into place (:func:`adadex.io.output_folder`);
    an existing dataset there is replaced only after the new one is complete (``overwrite=False``
    refuses instead). Anything else at ``path`` — a folder of other files, a file — is refused
    with :class:`~adadex.io.OutputExistsError` unless ``force=True``. ``info`` is stored in
    ``index.json`` (build parameters, rejection statistics …).

    Args:
        refs: the references (at least one; names unique, an unnamed one becomes ``ref<i>``).
        path: the dataset folder to write.
        splits: named splits, ``{name: {"train": [indices], "test": [indices]}}`` (checked
            against ``len(refs)``); default none.
        info: JSON-serializable build information for ``index.json``.
        overwrite: replace an existing dataset at ``path`` (default True); False refuses with
            :class:`~adadex.io.OutputExistsError`.
        force: replace whatever else is at ``path`` (default False: refuse).

    Returns:
        ``path``.
    """
    path = Path(path)
    if not refs:
        raise DatasetError(f"{path}: refusing to write an empty dataset")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"{path} exists (pass overwrite=True to replace it)")
    names = [r.name or f"ref{i:05d}" for i, r in enumerate(refs)]  # as _index_entry names them
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DatasetError(f"{path}: duplicate reference names {dup[:5]}")
    splits = check_splits(splits or {}, len(refs))
    entries, offset = [], 0
    for i, r in enumerate(refs):
        entries.append(_index_entry(r, offset, i))
        offset += r.num_frames
    index = {"version": FORMAT_VERSION, "num_references": len(refs), "num_frames": offset,
             "window_frames": WINDOW_FRAMES, "info": info or {}, "references": entries}

    with output_folder(path, "dataset", force=force, recognize=is_dataset, marker=False,
                       option="force=True (--force on the command line)") as tmp:
        _frames_tensordict(refs).memmap(str(tmp / "frames"))
        atomic_write_text(tmp / "splits.json", json.dumps(splits, indent=1))
        atomic_write_text(tmp / "index.json", json.dumps(index, indent=1, default=json_default))
    return path




class ReferenceDataset(Sequence):
    """A reference dataset folder, opened lazily: ``ds[i]`` reads reference ``i`` from the memmap.

    Attributes:
        entries: the ``index.json`` entries (dicts: name, offset, length, object, instruction, group …).
        splits: ``{split_name: {part: [indices]}}`` from ``splits.json``.
        frames: every frame of every reference as a memory-mapped TensorDict (for batched
            consumers such as the tracking environment, which index it by ``offset + t``).
        info: build information stored with the dataset.

    Args:
        path: the dataset folder (written by :func:`save_dataset`). A folder without
            ``index.json``, of another format version, or with an unreadable index or splits
            raises :class:`DatasetError`; the frames are mapped on first use.
    """

    def __init__(self, path):
        self.path = Path(path)
        index_file = self.path / "index.json"
        if not index_file.is_file():
            raise DatasetError(f"{self.path}: not a reference dataset (no index.json); "
                               f"build one with `adadex data build --out {self.path}`")
        # ValueError covers bad JSON, bad UTF-8 and check_splits' DatasetError (re-raised naming the folder).
        unreadable = (ValueError, KeyError, TypeError, AttributeError, OSError)
        try:
            index = json.loads(index_file.read_text())
            version = index.get("version")
        except unreadable as e:
            raise DatasetError(f"{self.path}: unreadable index or splits ({type(e).__name__}: {e})") from None
        if version != FORMAT_VERSION:
            raise DatasetError(f"{self.path}: format version {version}, expected {FORMAT_VERSION}")
        try:
            self.splits = check_splits(json.loads((self.path / "splits.json").read_text()),
                                       index["num_references"])
            self.entries: list[dict] = index["references"]
            self.info: dict = index.get("info", {})
            self.num_frames: int = index["num_frames"]
            if len(self.entries) != index["num_references"]:
                raise KeyError(f"{len(self.entries)} references, num_references is {index['num_references']}")
        except unreadable as e:
            raise DatasetError(f"{self.path}: unreadable index or splits ({type(e).__name__}: {e})") from None
        self._frames = None

    @property
    def frames(self):
        if self._frames is None:   # checked before caching, so every access fails
            self._frames = _open_frames(self.path, self.num_frames)
        return self._frames

    def __getstate__(self):        # the frames map the files again in another process
        return {**self.__dict__, "_frames": None}

    def __len__(self) -> int:
        return len(self.entries)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n = len(self)
        if not -n <= i < n:
            raise ReferenceIndexError(f"{self.path}: reference index {i} out of range for a dataset of {n} "
                                      f"(0 … {n - 1})")
        i = operator.index(i) % n
        check_frames(self, [i])
        e = self.entries[i]
        sl = self.frames[e["offset"]: e["offset"] + e["length"]]
        arr = {k: sl[k].numpy().astype(np.float64) for k in _FRAME_FIELDS}
        return Reference(
            hand_joint_pos=arr["hand_joint_pos"], hand_link_pose=_renormalized(arr["hand_link_pose"]),
            object_pose=_renormalized(arr["object_pose"]), object_name=e["object"],
            instruction=e["instruction"], group_id=e["group"], fps=e["fps"],
            human_keypoints=arr["human_keypoints"] if e["has_keypoints"] else None,
            retarget_residual=arr["retarget_residual"] if e["has_residual"] else None,
            meta=e["meta"], name=e["name"])

    def __iter__(self) -> Iterator[Reference]:
        for i in range(len(self)):
            yield self[i]

    def split(self, name: str, part: str) -> list[int]:
        """Indices of ``part`` (``"train"``/``"test"``) of split ``name`` (``"unseen_trajectory"`` …)."""
        if name not in self.splits:
            raise SplitError(f"{self.path}: no split {name!r}; available: {sorted(self.splits)}")
        if part not in self.splits[name]:
            raise SplitError(f"{self.path}: split {name!r} has no part {part!r}; available: "
                           f"{sorted(self.splits[name])}")
        return list(self.splits[name][part])

    def __repr__(self) -> str:
        return f"ReferenceDataset({str(self.path)!r}, {len(self)} references, {self.num_frames} frames)"


def _renormalized(pose: np.ndarray) -> np.ndarray:
    """Undo float32 rounding of the quaternion part of stored poses."""
    out = pose.copy()
    q = out[..., 3:]
    out[..., 3:] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return out


#: Trailing shape of each frame field, as stored (float32).
_FRAME_TAILS = {"hand_joint_pos": (NUM_JOINTS,), "hand_link_pose": (len(TRACKED_SITES), 7), "object_pose": (7,),
                "human_keypoints": (NUM_KEYPOINTS, 3), "retarget_residual": ()}


def _open_frames(path: Path, num_frames: int):
    """The frames of the dataset at ``path`` as a TensorDict of read-only (copy-on-write) memory maps.

    Every file is checked against ``index.json``'s frame count before it is mapped, so a truncated or
    missing file is an error naming it (a writable map would silently grow it back with zeros).
    """
    import torch
    from tensordict import TensorDict

    folder = path / "frames"
    meta_file = folder / "meta.json"
    try:
        meta = json.loads(meta_file.read_text(encoding="utf-8"))
        stored = int(meta["shape"][0])
    except (OSError, ValueError, KeyError, TypeError, IndexError) as e:
        raise DatasetError(f"{meta_file}: missing or unreadable ({type(e).__name__}: {e}); "
                           f"the dataset is incomplete, rebuild it") from None
    if stored != num_frames:
        raise DatasetError(f"{path}: index.json counts {num_frames} frames, frames/ holds {stored}")
    arrays = {}
    for key, tail in _FRAME_TAILS.items():
        f = folder / f"{key}.memmap"
        want = num_frames * int(np.prod(tail, dtype=np.int64)) * 4
        try:
            size = f.stat().st_size
        except OSError:
            raise DatasetError(f"{f}: missing; the dataset is incomplete, rebuild it") from None
        if size != want:
            raise DatasetError(f"{f}: {size} bytes, expected {want} ({num_frames} frames of {key} as float32); "
                               f"the file is truncated or damaged, rebuild the dataset")
        arr = np.memmap(f, dtype=np.float32, mode="c", shape=(num_frames, *tail)) if want else \
            np.zeros((num_frames, *tail), np.float32)
        arrays[key] = torch.from_numpy(arr)
    return TensorDict(arrays, batch_size=[num_frames])


def check_split(split) -> tuple[str, str] | None:
    """``split`` as a ``(name, part)`` pair (or ``None``: all references); anything else is a
    :class:`DatasetError` — a plain string such as ``"unseen_trajectory"`` would be unpacked letter
    by letter otherwise.

    >>> check_split(["unseen_object", "test"])
    ('unseen_object', 'test')
    """
    if split is None:
        return None
    if not isinstance(split, (str, bytes)):
        try:
            pair = tuple(split)
        except TypeError:
            pair = ()
        if len(pair) == 2 and all(isinstance(x, str) for x in pair):
            return pair
    raise DatasetError(f"split: expected (name, part) such as ('unseen_trajectory', 'train'), or None for all "
                       f"references; got {split!r}")


def check_frames(dataset: ReferenceDataset, indices) -> None:
    """Check every stored frame of references ``indices`` of ``dataset`` at once: finite values, unit
    quaternions (within :data:`QUAT_NORM_TOLERANCE`, plus float32 rounding) and joints within their limits
    (plus :data:`JOINT_LIMIT_TOLERANCE`). The one check used by ``dataset[i]`` and by the tracking
    environment; raises the :class:`ReferenceError` subclass of the first problem, naming the dataset,
    the reference (index and name) and the frame within it.
    """
    entries = dataset.entries
    idx = np.asarray(sorted({int(i) for i in indices}), dtype=np.int64)
    if idx.size == 0:
        return
    starts = np.array([entries[i]["offset"] for i in idx], dtype=np.int64)
    lengths = np.array([entries[i]["length"] for i in idx], dtype=np.int64)
    owner = np.repeat(np.arange(idx.size), lengths)               # position in idx of each frame
    rows = np.repeat(starts - np.cumsum(lengths) + lengths, lengths) + np.arange(int(lengths.sum()))
    frames = dataset.frames
    whole = rows.size == frames.batch_size[0] and np.array_equal(rows, np.arange(rows.size))

    def get(key):
        a = frames[key].numpy()
        return a if whole else a[rows]

    def where(k: int) -> str:
        r = int(idx[owner[k]])
        return f"{dataset.path}: reference {r} ({entries[r]['name']!r}), frame {int(rows[k] - starts[owner[k]])}"

    q, link, obj = get("hand_joint_pos"), get("hand_link_pose"), get("object_pose")
    for name, a in (("hand_joint_pos", q), ("hand_link_pose", link), ("object_pose", obj)):
        bad = ~np.isfinite(a.reshape(len(a), -1)).all(axis=1)
        if bad.any():
            k = int(np.argmax(bad))
            raise ReferenceValueError(f"{where(k)}: {name}: non-finite value "
                                      f"{a[k].ravel()[~np.isfinite(a[k].ravel())][0]}")
    tol = QUAT_NORM_TOLERANCE + 1e-5          # stored as float32
    for name, quats in (("hand_link_pose", link[..., 3:]), ("object_pose", obj[:, 3:])):
        err = np.abs(np.linalg.norm(quats.astype(np.float64), axis=-1) - 1.0).reshape(len(quats), -1).max(axis=1)
        if (err > tol).any():
            k = int(np.argmax(err > tol))
            norm = np.linalg.norm(quats[k].astype(np.float64), axis=-1).ravel()
            worst = norm[int(np.argmax(np.abs(norm - 1)))]
            raise QuaternionNormError(f"{where(k)}: {name}: quaternion norm {worst:.6f}, "
                                      f"expected 1 ± {QUAT_NORM_TOLERANCE}")
    lim = joint_limits()
    over = np.maximum(lim[:, 0] - q, q - lim[:, 1])
    bad = (over > JOINT_LIMIT_TOLERANCE).any(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        j = int(np.argmax(over[k]))
        raise JointLimitError(f"{where(k)}: joint {JOINT_NAMES[j]} is {q[k, j]:+.4f} rad, outside "
                              f"[{lim[j, 0]:+.4f}, {lim[j, 1]:+.4f}] by {over[k, j]:.4f} "
                              f"(tolerance {JOINT_LIMIT_TOLERANCE})")


def episode_references(dataset: ReferenceDataset, split: tuple[str, str] | None, window: int = WINDOW_FRAMES
                       ) -> list[int]:
    """Indices of the references in ``split`` (``None``: all) long enough for a ``window``-frame episode.

    Args:
        dataset: the reference dataset.
        split: ``(split name, part)``, e.g. ``("unseen_trajectory", "train")``; None: every reference.
        window: the episode's length in frames (default ``WINDOW_FRAMES``); a reference qualifies
            if this many frames follow its window start.
    """
    idx = list(range(len(dataset))) if split is None else dataset.split(*split)
    return [i for i in idx if dataset.entries[i]["window_start"] is not None
            and dataset.entries[i]["window_start"] + window <= dataset.entries[i]["length"]]
