"""The paper's figures from evaluation results: the ablation bars, Fig. 4–6 data and plots.

The Table-1 pipeline evaluates every row (baselines, the tracker, the modulated trackers) on both
splits under both conditions and then draws:

* :func:`plot_ablation` — one bar per row and (split, condition), with 95 % intervals over seeds;
* :func:`object_paths` / :func:`plot_object_paths` — Fig. 4: the object's path in the table plane as
  the dataset gives it (original), as the modulated tracker was asked to follow it (modulated: the
  reference the policy saw, with the R channel's edit), and as the simulation executed it;
* :func:`decoded_latents` / :func:`plot_latent_decoding` — Fig. 5: the object latents the tracker
  saw (with the O channel's edit) decoded by the point-cloud autoencoder, against the object;
* :func:`plot_data_scaling` — Fig. 6: success against the fraction of the training set;
* :func:`channel_usage` / :func:`plot_channel_usage` — how much each modulator uses each of its
  channels (mean |action| per entry): an ablation that does not order as the paper's often has a
  channel its modulator leaves unused.

Where the modulated inputs live in a rollout of :func:`adadex.eval.evaluate.evaluate` run with
:func:`adadex.transforms.policy.make_policy`: the reference entries show R's carried edit (row 0,
offset 0, is final for the current frame: R moves rows 1, 2, 4, 12 only), whereas the O edit is
applied inside the policy call, so ``("object", "latent")`` holds the unmodulated latent and
:func:`decoded_latents` re-applies the O channel to the stored modulator action
``("modulation", "sample")``.

Example
-------
>>> cell = {"tracker": {"completion_pct": 60.0, "completion_pct_ci95": [50.0, 70.0]},
...         "ROT": {"completion_pct": 75.0, "completion_pct_ci95": None}}
>>> table = {"unseen_trajectory": {"nominal": cell}}
>>> import tempfile, pathlib
>>> out = plot_ablation(table, pathlib.Path(tempfile.mkdtemp()) / "ablation.png")
>>> out.read_bytes()[:4] == b"\\x89PNG"
True
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from adadex.data.reference import ReferenceDataset
from adadex.envs.observation import OBJECT_LATENT, OBJECT_POSE, REF_OBJECT_POSE
from adadex.errors import ConfigError
from adadex.eval.table1 import CONDITIONS, ROW_LABELS, ROWS, SPLITS
from adadex.io import atomic_write
from adadex.modules.channels import CHANNELS, LATENT, ModulationConfig, ModulationLayout
from adadex.modules.encoder import chamfer_distance
from adadex.modules.modulator_view import LAST_ACTION
from adadex.sim.objects import get_object
from adadex.transforms.modulation import LatentModulation
from adadex.transforms.policy import SAMPLE

PATHS = ("original", "modulated", "executed")

_METRIC_LABELS = {"completion_pct": "completion success %", "mean_error_pct": "mean-error success %",
                  "success_mean_error_pct": "mean-error success %",
                  "object_completion_pct": "object completion % (T_o ≤ 5 cm)"}
_ROW_COLOURS = {"replay": "#9e9e9e", "ppo": "#bdbdbd", "il_rl": "#757575", "tracker": "#1f77b4",
                "R": "#ff7f0e", "RT": "#d62728", "ROT": "#2ca02c", "O": "#9467bd"}


def _finite(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ConfigError(f"{name} must be finite, got {v}")
    return v


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> Path:
    plt = _pyplot()
    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------------------------
# Ablation bars


def _ablation_cells(table, metric: str) -> dict[tuple[str, str], dict[str, tuple[float, list | None]]]:
    """{(split, condition): {row: (value, ci95 or None)}} in SPLITS × CONDITIONS × ROWS order, checked."""
    if not isinstance(table, Mapping) or not table:
        raise ConfigError(f"plot_ablation: table must be a non-empty {{split: {{condition: {{row: …}}}}}} dict, "
                          f"got {type(table).__name__} {table!r:.80}")
    cells = {}
    for split, conditions in table.items():
        if split not in SPLITS:
            raise ConfigError(f"plot_ablation: unknown split {split!r}; expected one of {SPLITS}")
        if not isinstance(conditions, Mapping):
            raise ConfigError(f"plot_ablation: table[{split!r}] must be a {{condition: …}} dict")
        for condition, rows in conditions.items():
            if condition not in CONDITIONS:
                raise ConfigError(f"plot_ablation: unknown condition {condition!r} in table[{split!r}]; "
                                  f"expected one of {CONDITIONS}")
            if not isinstance(rows, Mapping):
                raise ConfigError(f"plot_ablation: table[{split!r}][{condition!r}] must be a {{row: …}} dict")
            for row in rows:
                if row not in ROWS:
                    raise ConfigError(f"plot_ablation: unknown row {row!r} in table[{split!r}][{condition!r}]; "
                                      f"expected one of {ROWS}")
    for split, condition in itertools.product(SPLITS, CONDITIONS):
        rows = table.get(split, {}).get(condition)
        if not rows:
            continue
        cell = {}
        for row in (r for r in ROWS if r in rows):
            where = f"table[{split!r}][{condition!r}][{row!r}]"
            entry = rows[row]
            if not isinstance(entry, Mapping) or metric not in entry:
                raise ConfigError(f"plot_ablation: {where} has no {metric!r} entry")
            value = _finite(f"plot_ablation: {where}[{metric!r}]", entry[metric])
            ci = entry.get(f"{metric}_ci95")
            if ci is not None:
                if not isinstance(ci, Sequence) or len(ci) != 2:
                    raise ConfigError(f"plot_ablation: {where}[{metric + '_ci95'!r}] must be [lo, hi] or None, "
                                      f"got {ci!r}")
                ci = [_finite(f"plot_ablation: {where}[{metric + '_ci95'!r}]", c) for c in ci]
                if ci[0] > ci[1]:
                    raise ConfigError(f"plot_ablation: {where}[{metric + '_ci95'!r}] has lo > hi: {ci}")
            cell[row] = (value, ci)
        cells[(split, condition)] = cell
    if not cells:
        raise ConfigError("plot_ablation: the table holds no row to plot")
    return cells


def plot_ablation(table: dict, path, *, metric: str = "completion_pct", title: str = "") -> Path:
    """The ablation bar chart: one panel per (split, condition), one bar per row in :data:`ROWS` order.

    Args:
        table: ``{split: {condition: {row: {metric: value, f"{metric}_ci95": [lo, hi] | None}}}}``
            (:func:`adadex.eval.table1.aggregate`); missing splits, conditions and rows are left out.
        path: the PNG to write.
        metric: the entry to plot, e.g. ``"completion_pct"`` or ``"mean_error_pct"``.
        title: the figure's title (default: the metric's label).

    Bars show the value, with an error bar over the 95 % interval when there is one. Raises
    :class:`ConfigError` naming the entry for unknown names, missing or non-finite values.
    """
    cells = _ablation_cells(table, metric)
    splits = [s for s in SPLITS if any(k[0] == s for k in cells)]
    conditions = [c for c in CONDITIONS if any(k[1] == c for k in cells)]
    rows = [r for r in ROWS if any(r in cell for cell in cells.values())]
    ylabel = _METRIC_LABELS.get(metric, metric)
    percent = metric.endswith("_pct")
    plt = _pyplot()
    fig, axes = plt.subplots(len(splits), len(conditions), squeeze=False, sharey=True,
                             figsize=(max(4.5, 0.75 * len(rows) + 1.5) * len(conditions), 3.6 * len(splits)))
    x = np.arange(len(rows))
    for (i, split), (j, condition) in itertools.product(enumerate(splits), enumerate(conditions)):
        ax = axes[i][j]
        ax.set_title(f"{split.replace('_', ' ')}, {condition}", fontsize=10)
        cell = cells.get((split, condition))
        if cell is None:
            ax.text(0.5, 0.5, "not evaluated", ha="center", va="center", transform=ax.transAxes, color="0.5")
            ax.set_xticks([])
            continue
        xs = [x[rows.index(r)] for r in cell]
        values = [v for v, _ in cell.values()]
        # a success rate lies in [0, 100]: a t-interval over few seeds can reach past it, the bar cannot
        clip = (lambda lo, hi: (max(lo, 0.0), min(hi, 100.0))) if percent else (lambda lo, hi: (lo, hi))
        yerr = np.array([[max(v - clip(*ci)[0], 0.0), max(clip(*ci)[1] - v, 0.0)] if ci is not None
                         else [np.nan, np.nan] for v, ci in cell.values()]).T
        bars = ax.bar(xs, values, width=0.7, color=[_ROW_COLOURS[r] for r in cell],
                      yerr=yerr, capsize=3, error_kw={"elinewidth": 1})
        ax.bar_label(bars, labels=[f"{v:.1f}" if percent else f"{v:.3g}" for v in values], fontsize=7,
                     padding=2)
        ax.set_xticks(x, [ROW_LABELS[r] for r in rows], rotation=35, ha="right", fontsize=8)
        ax.grid(axis="y", alpha=0.3)
        if j == 0:
            ax.set_ylabel(ylabel)
    if percent:
        axes[0][0].set_ylim(0, 110)
    fig.suptitle(title or ylabel)
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------------------------
# Fig. 4: object paths


def _check_rollout(rollout, world, what: str) -> int:
    if not hasattr(rollout, "batch_size") or len(rollout.batch_size) != 2:
        raise ConfigError(f"{what}: rollout must be a TensorDict of batch shape [B, T] (one evaluation chunk), "
                          f"got {getattr(rollout, 'batch_size', type(rollout).__name__)}")
    B, T = rollout.batch_size
    if isinstance(world, bool) or not isinstance(world, (int, np.integer)) or not 0 <= world < B:
        raise ConfigError(f"{what}: world must be an integer in [0, {B}), got {world!r}")
    if T < 1:
        raise ConfigError(f"{what}: the rollout has no frame")
    return int(world)


def episode_length(rollout, world: int) -> int:
    """Frames of ``world``'s episode in ``rollout``: up to and including the step whose
    ``("next", "done")`` is first set (all frames when none is)."""
    world = _check_rollout(rollout, world, "episode_length")
    done = rollout.get(("next", "done"), None)
    T = rollout.batch_size[1]
    if done is None:
        return T
    hit = torch.nonzero(done[world].reshape(T)).flatten()
    return int(hit[0]) + 1 if len(hit) else T


def object_paths(rollout, dataset, references: Sequence[int], world: int) -> dict[str, np.ndarray]:
    """Fig. 4 data of one world of one evaluation chunk: ``{"original", "modulated", "executed"}``,
    each ``(T, 3)`` object positions in metres over the world's episode (cut after its first done).

    Args:
        rollout: one of ``evaluate(..., keep_rollouts=True)["rollouts"]``, batch shape [B, T].
        dataset: the evaluated :class:`ReferenceDataset` (or its folder).
        references: the chunk's dataset indices; world ``w`` tracks ``references[w]``.
        world: the world to read.

    ``original`` is the dataset reference over the episode's frames (frame ``t`` of the episode is
    the reference's frame ``window_start + t``, as :class:`~adadex.envs.tracking.TrackingEnv` maps
    it); ``modulated`` the reference the policy saw at offset 0 (``("reference", "object_pose")``
    row 0, which carries the R channel's edit — equal to ``original`` without R); ``executed`` the
    simulated object, ``("object", "pose")``.
    """
    world = _check_rollout(rollout, world, "object_paths")
    B = rollout.batch_size[0]
    refs = [int(r) for r in references]
    if len(refs) != B:
        raise ConfigError(f"object_paths: references must list the chunk's {B} dataset indices (one per world), "
                          f"got {len(refs)}")
    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    ref = refs[world]
    if not 0 <= ref < len(ds):
        raise ConfigError(f"object_paths: references[{world}] = {ref} is not an index of {ds.path} "
                          f"({len(ds)} references)")
    stored = rollout.get(("privileged", "reference_index"), None)
    if stored is not None and int(stored[world, 0]) != ref:
        raise ConfigError(f"object_paths: world {world} of the rollout tracks reference {int(stored[world, 0])}, "
                          f"not references[{world}] = {ref}: references must be this chunk's list")
    entry = ds.entries[ref]
    n = episode_length(rollout, world)
    if entry["window_start"] is None or entry["window_start"] + n > entry["length"]:
        raise ConfigError(f"object_paths: reference {entry['name']!r} has no {n}-frame episode window")
    base = entry["offset"] + entry["window_start"]
    original = ds.frames["object_pose"][base:base + n, :3].double().numpy()
    modulated = rollout.get(REF_OBJECT_POSE)[world, :n, 0, :3].double().numpy()
    executed = rollout.get(OBJECT_POSE)[world, :n, :3].double().numpy()
    return {"original": original, "modulated": modulated, "executed": executed}


def _check_paths(paths) -> dict[str, np.ndarray]:
    if not isinstance(paths, Mapping) or set(PATHS) - set(paths):
        raise ConfigError(f"plot_object_paths: paths must hold {PATHS}, got "
                          f"{sorted(paths) if isinstance(paths, Mapping) else type(paths).__name__}")
    out = {k: np.asarray(paths[k], dtype=np.float64) for k in PATHS}
    n = len(out["original"])
    for k, v in out.items():
        if v.ndim != 2 or v.shape[1] != 3 or len(v) != n or not n:
            raise ConfigError(f"plot_object_paths: paths[{k!r}] must be (T, 3) with the same T ≥ 1 for all paths, "
                              f"got {v.shape} (original: {out['original'].shape})")
        if not np.isfinite(v).all():
            raise ConfigError(f"plot_object_paths: paths[{k!r}] has a non-finite value at frame "
                              f"{int(np.argwhere(~np.isfinite(v))[0, 0])}")
    return out


def plot_object_paths(paths: dict[str, np.ndarray], path, *, title: str = "") -> Path:
    """Fig. 4: the original (dashed), modulated and executed object paths in the table's x–y plane
    (cm, equal aspect), each with a start (○) and an end (■) marker, as a PNG."""
    paths = _check_paths(paths)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.2, 4.6))
    styles = {"original": dict(ls="--", color="0.35"), "modulated": dict(ls="-", color="#ff7f0e"),
              "executed": dict(ls="-", color="#1f77b4")}
    for name in PATHS:
        p = paths[name][:, :2] * 100.0
        line, = ax.plot(p[:, 0], p[:, 1], lw=1.6, label=name, **styles[name])
        ax.plot(*p[0], "o", mfc="none", color=line.get_color(), ms=7)
        ax.plot(*p[-1], "s", color=line.get_color(), ms=5)
    ax.plot([], [], "o", mfc="none", color="k", label="start")
    ax.plot([], [], "s", color="k", label="end")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (cm)")
    ax.set_ylabel("y (cm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title or f"object path ({len(paths['original'])} frames)", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------------------------
# Fig. 5: decoded latents


def _latent_layout(dim: int, channels) -> ModulationLayout:
    """The channel layout of a modulator sample of ``dim`` entries (given, or the unique subset that fits)."""
    if channels is not None:
        layout = ModulationLayout(channels)
        if layout.dim != dim:
            raise ConfigError(f"decoded_latents: the rollout's {SAMPLE} has {dim} entries, channels "
                              f"{layout.name} have {layout.dim}")
        return layout
    names = list(CHANNELS)
    fits = [ModulationLayout(sub) for k in range(1, len(names) + 1) for sub in itertools.combinations(names, k)
            if ModulationLayout(sub).dim == dim]
    if len(fits) != 1:
        raise ConfigError(f"decoded_latents: cannot tell the channels of a {dim}-entry modulator sample "
                          f"({'several fit: ' + ', '.join(f.name for f in fits) if fits else 'none fits'}); "
                          "pass channels=…")
    return fits[0]


def decoded_latents(rollout, world: int, steps: int = 4, *, channels=None,
                    config: ModulationConfig = ModulationConfig()) -> tuple[list[int], torch.Tensor]:
    """Fig. 5 data: the object latent the tracker saw at ``steps`` evenly spaced frames of ``world``'s
    episode (before its first done) → (frame indices, (steps, 64) latents).

    The rollout stores the env's latent, ``("object", "latent")``; a :func:`make_policy` graph applies
    the O channel inside its call, so with O on the latent is rebuilt here from the stored modulator
    action ``("modulation", "sample")`` by the O channel's own transform (``channels``: the policy's
    channels, found from the sample's size when not given; ``config``: its λ's). Without a sample
    (an unmodulated policy) or without O, the stored latent is what the tracker saw.
    """
    world = _check_rollout(rollout, world, "decoded_latents")
    n = episode_length(rollout, world)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 1 <= steps <= n:
        raise ConfigError(f"decoded_latents: steps must be an integer in [1, {n}] (world {world}'s episode has "
                          f"{n} frames), got {steps!r}")
    frames = [int(round(f)) for f in np.linspace(0, n - 1, int(steps))]
    latent = rollout.get(OBJECT_LATENT)[world, frames].float()
    sample = rollout.get(SAMPLE, None)
    if sample is not None:
        layout = _latent_layout(sample.shape[-1], channels)
        if "O" in layout:
            td = TensorDict({OBJECT_LATENT: latent.clone(), LATENT: layout.split(sample[world, frames])[LATENT]},
                            batch_size=[len(frames)])
            latent = LatentModulation(config)._inv_call(td).get(OBJECT_LATENT)
    return frames, latent


def _check_latents(latents, frames, original_latent, dim: int) -> None:
    if not isinstance(latents, torch.Tensor) or latents.dim() != 2 or latents.shape[1] != dim or not len(latents):
        raise ConfigError(f"plot_latent_decoding: latents must be a (steps, {dim}) tensor, got "
                          f"{tuple(latents.shape) if isinstance(latents, torch.Tensor) else type(latents).__name__}")
    if len(frames) != len(latents):
        raise ConfigError(f"plot_latent_decoding: {len(frames)} frames for {len(latents)} latents")
    if not torch.isfinite(latents).all():
        raise ConfigError(f"plot_latent_decoding: latents has a non-finite value in row "
                          f"{int(torch.nonzero(~torch.isfinite(latents))[0, 0])}")
    if original_latent is not None and (not isinstance(original_latent, torch.Tensor)
                                        or original_latent.shape != (dim,)
                                        or not torch.isfinite(original_latent).all()):
        raise ConfigError(f"plot_latent_decoding: original_latent must be a finite ({dim},) tensor, got "
                          f"{getattr(original_latent, 'shape', type(original_latent).__name__)}")


@torch.no_grad()
def plot_latent_decoding(autoencoder, latents: torch.Tensor, frames: list[int], object_name: str, path, *,
                         original_latent: torch.Tensor | None = None, points: int | None = None,
                         seed: int = 0) -> Path:
    """Fig. 5: each latent decoded by ``autoencoder`` (a
    :class:`~adadex.modules.encoder.PointCloudAutoencoder`) against the object's surface points, one
    3-D panel per frame (a first one for ``original_latent``, the unmodulated latent, when given).

    Both clouds are centred (the object on its bounding-box centre, as the encoder sees it), in cm;
    each title gives the frame and the RMS nearest-neighbour distance between the clouds (mm).
    ``points`` object points are sampled with ``seed`` (default: as many as the decoder outputs).
    """
    dim = autoencoder.config.latent_dim
    _check_latents(latents, frames, original_latent, dim)
    obj = get_object(object_name)
    n = int(points or autoencoder.config.decoded_points)
    cloud = torch.from_numpy(obj.point_cloud(n, seed=seed))
    target = autoencoder.normalise(cloud)[0] / autoencoder.config.unit_scale
    panels = [(f"frame {f}", z) for f, z in zip(frames, latents.float())]
    if original_latent is not None:
        panels.insert(0, ("original latent", original_latent.float()))
    z = torch.stack([p[1] for p in panels])
    decoded = autoencoder.eval().decode(z) / autoencoder.config.unit_scale
    rms_mm = chamfer_distance(decoded, target.expand(len(z), -1, -1)).sqrt() * 1e3
    half = 105.0 * max(float(target.abs().max()), float(decoded.abs().max()))
    plt = _pyplot()
    fig = plt.figure(figsize=(2.8 * len(panels), 3.3))
    t = target.numpy() * 100.0
    for k, ((label, _), d) in enumerate(zip(panels, decoded)):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        p = d.numpy() * 100.0
        ax.scatter(t[:, 0], t[:, 1], t[:, 2], s=2, c="0.3", alpha=0.35, label="object")
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=1.5, c=p[:, 2], cmap="plasma", label="decoded")
        for set_lim in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
            set_lim(-half, half)
        ax.set_box_aspect((1, 1, 1))
        ax.tick_params(labelsize=5)
        ax.set_title(f"{label}\nRMS {float(rms_mm[k]):.1f} mm", fontsize=8)
    fig.suptitle(f"{object_name}: decoded latents (colour) vs object points (grey), cm", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------------------------
# Fig. 6: data scaling


def plot_data_scaling(fractions, results: dict[str, list[tuple[float, float | None, float | None]]], path, *,
                      ylabel: str = "completion success %", title: str = "") -> Path:
    """Fig. 6: one line per named series against the fraction of the training set (log x, ticks at
    ``fractions``); each point ``(mean, lo, hi)`` gets an error bar when ``lo`` and ``hi`` are given."""
    fr = [_finite(f"plot_data_scaling: fractions[{i}]", f) for i, f in enumerate(fractions)]
    if not fr or any(f <= 0 for f in fr):
        raise ConfigError(f"plot_data_scaling: fractions must be a non-empty list of numbers > 0, got {fr}")
    if not isinstance(results, Mapping) or not results:
        raise ConfigError("plot_data_scaling: results must be a non-empty {series name: [(mean, lo, hi), …]} dict")
    series = {}
    for name, points in results.items():
        points = list(points)
        if len(points) != len(fr):
            raise ConfigError(f"plot_data_scaling: results[{name!r}] has {len(points)} points for {len(fr)} fractions")
        rows = []
        for i, pt in enumerate(points):
            where = f"plot_data_scaling: results[{name!r}][{i}]"
            if not isinstance(pt, Sequence) or len(pt) != 3:
                raise ConfigError(f"{where} must be (mean, lo, hi), got {pt!r}")
            mean = _finite(f"{where} mean", pt[0])
            if (pt[1] is None) != (pt[2] is None):
                raise ConfigError(f"{where}: give both lo and hi or neither, got {pt!r}")
            lo, hi = (None, None) if pt[1] is None else (_finite(f"{where} lo", pt[1]), _finite(f"{where} hi", pt[2]))
            if lo is not None and lo > hi:
                raise ConfigError(f"{where}: lo > hi in {pt!r}")
            rows.append((mean, lo, hi))
        series[name] = rows
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for name, rows in series.items():
        means = [m for m, _, _ in rows]
        line, = ax.plot(fr, means, "o-", label=name)
        ci = [(f, m, lo, hi) for f, (m, lo, hi) in zip(fr, rows) if lo is not None]
        if ci:
            xs, ms, los, his = map(np.array, zip(*ci))
            ax.errorbar(xs, ms, yerr=[np.maximum(ms - los, 0), np.maximum(his - ms, 0)], fmt="none",
                        ecolor=line.get_color(), capsize=3)
    ax.set_xscale("log")
    ticks = sorted(set(fr))
    ax.set_xticks(ticks, [f"{f:g}" for f in ticks])
    ax.minorticks_off()
    ax.set_xlabel("fraction of the training set")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def channel_usage(rollouts, channels) -> dict[str, float]:
    """How much a modulator uses each of its action entries: the mean |a| (0: unused, 1: saturated) of
    the modulator's action as the env applied it — the view's ``("next", "modulation", "last_action")``
    where the modulator reads a view (a modulator deciding every k steps holds its action in between),
    else the stored sample ``("modulation", "sample")`` — over every frame of ``rollouts`` (chunks
    of an evaluation with ``keep_rollouts``) before each world's first done, per entry of ``channels``
    (``"ref_hand"``, ``"latent"``, …)."""
    layout = ModulationLayout(channels)
    totals: dict[str, float] = {}
    frames = 0
    for td in rollouts:
        done = td.get(("next", "done")).reshape(td.batch_size).to(torch.bool)
        valid = ~(torch.cumsum(done.int(), 1) - done.int() > 0)
        applied = td.get(("next", *LAST_ACTION), None)
        for key, value in layout.split((td.get(SAMPLE) if applied is None else applied)[valid]).items():
            name = key[-1] if isinstance(key, tuple) else key
            totals[name] = totals.get(name, 0.0) + float(value.abs().reshape(value.shape[0], -1).mean(1).sum())
        frames += int(valid.sum())
    if frames == 0:
        raise ConfigError("channel_usage: the rollouts hold no frame")
    return {k: v / frames for k, v in totals.items()}


def plot_channel_usage(usage: Mapping[str, Mapping[str, float]], path, *, title: str = "") -> Path:
    """Grouped bars: per modulator (``{row: channel_usage(...)}``), the mean |a| of each action entry."""
    if not usage or not all(usage.values()):
        raise ConfigError("plot_channel_usage: give {row: {entry: mean |a|}} with at least one entry each")
    entries = list(dict.fromkeys(e for u in usage.values() for e in u))
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(1.3 * len(entries) + 3, 3.6))
    width = 0.8 / len(usage)
    x = np.arange(len(entries))
    for i, (row, u) in enumerate(usage.items()):
        vals = [_finite(f"usage[{row!r}][{e!r}]", u[e]) if e in u else np.nan for e in entries]
        ax.bar(x + (i - (len(usage) - 1) / 2) * width, vals, width, label=ROW_LABELS.get(row, row),
               color=_ROW_COLOURS.get(row))
    ax.set_xticks(x, entries)
    ax.set_ylabel("mean |modulator action| (1 = saturated)")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    ax.set_title(title or "what each modulator uses")
    return _save(fig, path)
