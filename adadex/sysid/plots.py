"""Plots of the workbench (matplotlib, Agg): overlays, error heatmaps, the error falling by stage."""

from __future__ import annotations

import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def fig_to_png(fig) -> bytes:
    """The matplotlib figure ``fig`` as PNG bytes (110 dpi); the figure is closed."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def overlay(rec, sims: dict[str, np.ndarray], seq: int, joint: str):
    """Command, measurement and one or more model replays of one joint in one sequence (Fig. 8 style)."""
    j = list(rec.joint_names).index(joint)
    fig, ax = plt.subplots(figsize=(7.5, 2.8))
    ax.plot(rec.time, np.degrees(rec.command[seq, :, j]), color="0.6", lw=1.2, ls="--", label="command")
    ax.plot(rec.time, np.degrees(rec.joint_pos[seq, :, j]), color="k", lw=1.4, label="measured")
    colors = ["tab:red", "tab:blue", "tab:green", "tab:purple"]
    for (name, q), c in zip(sims.items(), colors):
        ax.plot(rec.time, np.degrees(q[seq, :, j]), color=c, lw=1.1, label=name)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"{joint} (deg)")
    ax.set_title(rec.sequence_labels[seq], fontsize=9)
    ax.legend(fontsize=7, ncol=4, loc="upper right")
    ax.grid(alpha=0.3)
    return fig


def heatmap(rms: np.ndarray, joints, labels, title: str, vmax: float | None = None, *, log: bool = True):
    """Joint × sequence RMS error (deg), on a log colour scale by default (three decades below the
    largest error) so a joint failing by 0.05° shows next to one failing by 5°."""
    from matplotlib.colors import LogNorm

    fig, ax = plt.subplots(figsize=(max(4.0, 0.35 * len(joints) + 2), max(2.5, 0.12 * len(labels) + 1.5)))
    deg = np.degrees(rms)
    if log:
        top = vmax if vmax else max(float(deg.max()), 1e-6)
        im = ax.imshow(np.maximum(deg, top * 1e-3), aspect="auto", cmap="magma", norm=LogNorm(top * 1e-3, top))
    else:
        im = ax.imshow(deg, aspect="auto", cmap="magma", vmin=0, vmax=vmax)
    ax.set_xticks(range(len(joints)), joints, rotation=60, fontsize=7)
    step = max(1, len(labels) // 40)
    ax.set_yticks(range(0, len(labels), step), [labels[i] for i in range(0, len(labels), step)], fontsize=5)
    ax.set_title(title, fontsize=9)
    fig.colorbar(im, ax=ax, label="RMS error (deg)")
    return fig


def error_fall(stages: list[str], per_joint: np.ndarray, joints, split: str):
    """Grouped bars: RMS error (deg) per joint at each stage (baseline → +effect 1 → …)."""
    n_st, n_j = per_joint.shape
    fig, ax = plt.subplots(figsize=(max(5.0, 0.9 * n_j + 2), 3.0))
    width = 0.8 / n_st
    x = np.arange(n_j)
    for i, st in enumerate(stages):
        ax.bar(x + (i - (n_st - 1) / 2) * width, np.degrees(per_joint[i]), width, label=st)
    ax.set_xticks(x, joints, rotation=45, fontsize=8)
    ax.set_ylabel("RMS error (deg)")
    ax.set_title(f"error per joint, {split} sequences", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(axis="y", alpha=0.3)
    return fig
