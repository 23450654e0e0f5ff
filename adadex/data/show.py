"""A picture of one hand–object reference (the paper's Fig. 7): the quickest check that
retargeting, generation or a dataset round trip produced what was meant.

:func:`plot_reference` writes one PNG:

* left, 3-D: the palm path coloured by time, the four fingertip paths, the object-centre path,
  start/end markers, the episode window (highlighted, its first frame marked) and the table top (z = 0),
  with equal scale on all axes;
* right, top-down X–Y: the same paths over the whole table, the robot base at the origin;
* below, when offscreen OpenGL rendering works: ``frames`` MuJoCo renders of the kinematic replay
  (joint positions and object pose set, no physics) at evenly spaced frames of the episode window.

Rendering needs an OpenGL backend. MuJoCo chooses one when it is imported (``MUJOCO_GL``), and after a
failed context creation another attempt can abort the process, so :func:`rendering_status` probes
each candidate in a subprocess first: ``MUJOCO_GL`` if set, else ``egl``, ``osmesa``, then ``glfw``
(which needs a display). The first that works is used in-process (importing ``mujoco.egl`` sets
``PYOPENGL_PLATFORM=egl`` if unset); the outcome is cached for the process.

Example::

    from adadex.data.reference import ReferenceDataset
    from adadex.data.show import plot_reference

    info = plot_reference(ReferenceDataset("data/refs")[0], "figs/ref0.png", frames=4)
    print(info["rendered"], info["render_note"])
"""

from __future__ import annotations

import importlib
import io
import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
from matplotlib import colors
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

from adadex.data.reference import WINDOW_FRAMES, Reference, ReferenceError, WindowTooShortError
from adadex.errors import ConfigError
from adadex.io import atomic_write_bytes
from adadex.sim.robot import NUM_JOINTS, TRACKED_SITES
from adadex.sim.scene import OBJECT_QPOS, TABLE_CENTER, TABLE_HALF_SIZE, build_scene_model

#: Size of one rendered frame, (height, width) px; within the scene's 640×480 offscreen buffer.
FRAME_SIZE = (240, 320)
_TIP_COLORS = ("tab:orange", "tab:pink", "tab:purple", "tab:brown")
_OBJECT_COLOR = "tab:red"
_PROBE = """import mujoco
m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size="0.1"/></worldbody></mujoco>')
r = mujoco.Renderer(m, 8, 8); d = mujoco.MjData(m); mujoco.mj_forward(m, d); r.update_scene(d); r.render()
"""
_STATUS: tuple | None = None  # (GLContext class or None, note), once probed


def _probe(name: str) -> str | None:
    """None if rendering works with ``MUJOCO_GL=name`` in a fresh interpreter, else why not."""
    try:
        p = subprocess.run([sys.executable, "-c", _PROBE], env=dict(os.environ, MUJOCO_GL=name),
                           capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"probe failed: {e}"
    if p.returncode == 0:
        return None
    lines = [ln.strip() for ln in p.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if re.match(r"^[\w.]*(Error|Exception)\b", ln)]
    return (errors or lines or [f"probe exited with status {p.returncode}"])[-1]


def _backend() -> tuple:
    global _STATUS
    if _STATUS is None:
        env = os.environ.get("MUJOCO_GL", "").strip().lower()
        failures = []
        for name in [env] if env else ["egl", "osmesa", "glfw"]:
            why = _probe(name)
            if why is None:
                try:
                    own = name == env or (not env and name == "glfw")  # the backend chosen at import
                    cls = getattr(mujoco, "GLContext") if own else importlib.import_module(f"mujoco.{name}").GLContext
                    _STATUS = (cls, f"rendered offscreen with MUJOCO_GL={name}")
                    break
                except Exception as e:  # noqa: BLE001 - any failure means "not available", with the reason
                    why = f"{type(e).__name__}: {e}"
            failures.append(f"MUJOCO_GL={name}: {why}")
        else:
            _STATUS = (None, "offscreen rendering unavailable (" + "; ".join(failures) + ")")
    return _STATUS


def rendering_status() -> tuple[bool, str]:
    """``(available, note)``: whether frames can be rendered in this process, and how or why not."""
    cls, note = _backend()
    return cls is not None, note


def _render_frames(ref: Reference, idx: list[int], context_cls) -> list[np.ndarray]:
    """RGB images of the kinematic replay at frames ``idx`` from a fixed camera over the table."""
    model = build_scene_model(ref.object_name)
    data = mujoco.MjData(model)
    h, w = FRAME_SIZE
    pts = np.concatenate([ref.hand_link_pose[idx[0]: idx[-1] + 1, 0, :3], ref.object_pose[idx[0]: idx[-1] + 1, :3]])
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = (pts.min(0) + pts.max(0)) / 2 + [0.0, 0.0, 0.05]
    cam.distance = max(1.1, 2.5 * float(np.ptp(pts, axis=0).max()))
    cam.azimuth, cam.elevation = 155.0, -30.0
    ctx = context_cls(w, h)
    ctx.make_current()
    con = None
    try:
        con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, con)
        scene, opt, rect = mujoco.MjvScene(model, maxgeom=10000), mujoco.MjvOption(), mujoco.MjrRect(0, 0, w, h)
        images = []
        for t in idx:
            data.qpos[:NUM_JOINTS] = ref.hand_joint_pos[t]
            data.qpos[OBJECT_QPOS] = ref.object_pose[t]
            mujoco.mj_forward(model, data)
            mujoco.mjv_updateScene(model, data, opt, None, cam, mujoco.mjtCatBit.mjCAT_ALL, scene)
            mujoco.mjr_render(rect, scene, con)
            rgb = np.empty((h, w, 3), np.uint8)
            mujoco.mjr_readPixels(rgb, None, rect, con)
            images.append(np.flipud(rgb))
        return images
    finally:
        if con is not None:
            con.free()
        ctx.free()


def _window(ref: Reference) -> tuple[tuple[int, int] | None, str]:
    try:
        w = ref.window()
        return (w.start, w.stop), f"episode frames {w.start}–{w.stop - 1}"
    except WindowTooShortError:
        pass
    try:
        s = ref.window_start()
    except WindowTooShortError:
        return None, "no episode window (the palm never leaves the object)"
    return (s, ref.num_frames), f"episode from frame {s}, only {ref.num_frames - s} of {WINDOW_FRAMES} frames"


def _draw_paths(ax, ref: Reference, window, norm, dims: int):
    """Palm (time-coloured), fingertips, object, markers on ``ax`` using the first ``dims`` coordinates."""
    poses = ref.hand_link_pose[:, :, :dims]
    palm, obj = poses[:, 0], ref.object_pose[:, :dims]
    line = (Line3DCollection if dims == 3 else LineCollection)(
        np.stack([palm[:-1], palm[1:]], 1), cmap="viridis", norm=norm, linewidths=2.5, zorder=3)
    line.set_array(np.arange(len(palm) - 1) / ref.fps)
    ax.add_collection(line)
    if window is not None:
        ax.plot(*palm[window[0]: window[1]].T, color="0.5", lw=8, alpha=0.25, solid_capstyle="round",
                label=f"episode window ({window[1] - window[0]} frames)")
    for i, name in enumerate(TRACKED_SITES[1:]):
        ax.plot(*poses[:, i + 1].T, lw=0.8, color=_TIP_COLORS[i], alpha=0.9, label=name)
    ax.plot(*obj.T, lw=2, color=_OBJECT_COLOR, label="object centre")
    for path in (palm, obj):
        ax.plot(*path[0][:, None], "o", ms=7, mfc="white", mec="k", zorder=5)
        ax.plot(*path[-1][:, None], "s", ms=7, mfc="k", mec="k", zorder=5)
    ax.plot([], [], "o", mfc="white", mec="k", label="start")  # legend entries for both paths' markers
    ax.plot([], [], "s", color="k", label="end")
    if window is not None:
        ax.plot(*palm[window[0]][:, None], "^", ms=10, color="crimson", zorder=6,
                label=f"window start (frame {window[0]})")
    return line


def plot_reference(ref: Reference, out, *, render: bool | None = None, frames: int = 4) -> dict:
    """Draw ``ref`` to the PNG ``out`` (see the module docstring); returns what was drawn.

    ``render``: None renders frames if offscreen rendering works, True requires it (RuntimeError
    saying why not), False never renders. The returned dict: ``path``, ``rendered``, ``render_note``
    (how frames were rendered, or why not), ``render_frames`` (frame indices, [] if none),
    ``window`` ([start, stop) or None), ``window_note`` and ``size`` ([width, height] px).
    """
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise ConfigError(f"{out}: plot_reference writes PNG, so the file name must end in .png")
    if out.is_dir():
        raise IsADirectoryError(f"{out} is a directory; pass a file path ending in .png")
    if int(frames) < 1:
        raise ConfigError(f"frames must be at least 1, got {frames}")
    T = ref.num_frames
    if T < 2:
        raise ReferenceError(f"reference {ref.name!r} has {T} frame(s); a path needs at least 2")
    window, window_note = _window(ref)
    images, idx, note = [], [], "not requested (render=False)"
    if render is not False:
        cls, note = _backend()
        if cls is None and render:
            raise RuntimeError(f"plot_reference(render=True): {note}")
        if cls is not None:
            lo, hi = window or (0, T)
            idx = [int(i) for i in np.linspace(lo, hi - 1, int(frames)).round()]
            try:
                images = _render_frames(ref, idx, cls)
            except Exception as e:  # noqa: BLE001 - reported, or raised when rendering is required
                if render:
                    raise RuntimeError(f"plot_reference(render=True): rendering failed: {e}") from e
                images, idx, note = [], [], f"rendering failed: {type(e).__name__}: {e}"

    fig = Figure(figsize=(13, 5.6 + (3.0 if images else 0.0)), dpi=100, layout="constrained")
    top, bottom = fig.subfigures(2, 1, height_ratios=[5.6, 3.0]) if images else (fig, None)
    ax3, axy = top.add_subplot(1, 2, 1, projection="3d"), top.add_subplot(1, 2, 2)
    norm = colors.Normalize(0.0, (T - 1) / ref.fps)

    _draw_paths(ax3, ref, window, norm, 3)
    pts = np.concatenate([ref.hand_link_pose[:, :, :3].reshape(-1, 3), ref.object_pose[:, :3]])
    lo, hi = np.minimum(pts.min(0), [np.inf, np.inf, 0.0]), np.maximum(pts.max(0), [-np.inf, -np.inf, 0.0])
    mid, half = (lo + hi) / 2, np.maximum((hi - lo) / 2 + 0.03, 0.05)  # table top in view, 3 cm margin
    lo, hi = mid - half, mid + half
    (tx, ty), (hx, hy, _) = TABLE_CENTER, TABLE_HALF_SIZE
    x0, x1 = np.clip([tx - hx, tx + hx], lo[0], hi[0])
    y0, y1 = np.clip([ty - hy, ty + hy], lo[1], hi[1])
    if x1 > x0 and y1 > y0 and lo[2] <= 0 <= hi[2]:
        ax3.add_collection3d(Poly3DCollection([[(x0, y0, 0), (x1, y0, 0), (x1, y1, 0), (x0, y1, 0)]],
                                              facecolor=(0.55, 0.42, 0.3, 0.15), edgecolor="saddlebrown"))
    ax3.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]),
            xlabel="x (m)", ylabel="y (m)", zlabel="z (m)", title="3-D paths (table top at z = 0)")
    ax3.set_box_aspect(hi - lo)

    axy.add_patch(Rectangle((tx - hx, ty - hy), 2 * hx, 2 * hy, facecolor=(0.55, 0.42, 0.3, 0.15),
                            edgecolor="saddlebrown", label="table top"))
    axy.plot(0, 0, "P", color="0.3", ms=9, label="robot base")
    line = _draw_paths(axy, ref, window, norm, 2)
    axy.set(aspect="equal", xlabel="x (m)", ylabel="y (m)", title="top view (X–Y)")
    axy.autoscale_view()
    axy.legend(loc="upper left", bbox_to_anchor=(1.25, 1.0), fontsize=8, frameon=False)
    fig.colorbar(line, ax=axy, label="palm path: time (s)", shrink=0.8)

    for k, (t, img) in enumerate(zip(idx, images)):
        ax = bottom.add_subplot(1, len(images), k + 1)
        ax.imshow(img)
        ax.set_title(f"frame {t}  (t = {t / ref.fps:.1f} s)", fontsize=9)
        ax.axis("off")
    name = f" · {ref.name}" if ref.name else ""
    fig.suptitle(f"“{ref.instruction}”\n{ref.object_name} · group {ref.group_id} · {T} frames · "
                 f"{ref.duration:.1f} s at {ref.fps:g} Hz · {window_note}{name}", fontsize=11)

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    png = buf.getvalue()
    atomic_write_bytes(out, png)
    width, height = struct.unpack(">II", png[16:24])
    return {"path": str(out), "rendered": bool(images), "render_note": note, "render_frames": idx,
            "window": list(window) if window else None, "window_note": window_note, "size": [width, height]}
