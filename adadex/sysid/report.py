"""Watch the error fall: stage-by-stage comparison and a self-contained HTML report.

:func:`error_stages` replays a recording under the nominal model and then under the patch's
effects added one at a time (baseline → +effect 1 → +effect 1 + effect 2 …), and reports the RMS
error per joint and overall on training and held-out sequences. :func:`write_report` renders that,
the localization findings, an optional diagnosis, overlays and heatmaps into one HTML file with
the plots embedded as base64 PNGs — it opens offline, nothing is fetched.
"""

from __future__ import annotations

import base64
import html
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from adadex.io import atomic_write_text
from adadex.sim.effects import get_effect
from adadex.sim.patch import ModelPatch
from adadex.sysid import plots
from adadex.sysid.compare import Comparison, heldout_mask, localize


@dataclass(kw_only=True)
class Stages:
    """The report's stages (nominal model, then each effect added): their names, patches, comparisons,
    and which sequences are held out."""

    names: list[str]
    patches: list[ModelPatch]
    comparisons: list[Comparison]
    heldout: np.ndarray                 # (S,) bool

    def per_joint(self, split: str) -> np.ndarray:
        """(n_stages, J) RMS error per joint on ``train``/``heldout``/``all`` sequences."""
        sel = {"train": ~self.heldout, "heldout": self.heldout, "all": np.ones_like(self.heldout)}[split]
        if not sel.any():
            sel = np.ones_like(self.heldout)
        return np.array([np.sqrt((c.error[sel] ** 2).mean(axis=(0, 1))) for c in self.comparisons])

    def overall(self, split: str) -> np.ndarray:
        sel = {"train": ~self.heldout, "heldout": self.heldout, "all": np.ones_like(self.heldout)}[split]
        if not sel.any():
            sel = np.ones_like(self.heldout)
        return np.array([float(np.sqrt((c.error[sel] ** 2).mean())) for c in self.comparisons])

    def to_dict(self) -> dict:
        joints = list(self.comparisons[0].joint_names)
        out = {"stages": self.names, "patches": [p.to_dict() for p in self.patches]}
        for split in ("train", "heldout"):
            out[split] = {"overall_rms_rad": self.overall(split).tolist(),
                          "per_joint_rms_rad": {j: col.tolist() for j, col in zip(joints, self.per_joint(split).T)}}
        return out

    def table(self) -> str:
        joints = list(self.comparisons[0].joint_names)
        tr, ho = self.per_joint("train"), self.per_joint("heldout")
        lines = [f"{'stage':<40} {'train RMS':>10} {'held-out RMS':>13}   (deg)"]
        for i, n in enumerate(self.names):
            lines.append(f"{n:<40} {np.degrees(self.overall('train')[i]):10.3f} {np.degrees(self.overall('heldout')[i]):13.3f}")
        moved = [k for k in range(len(joints)) if abs(tr[0, k] - tr[-1, k]) > 1e-12]
        if moved:
            lines.append("per joint, held-out RMS (deg): " + "; ".join(
                f"{joints[k]} " + " → ".join(f"{np.degrees(ho[i, k]):.3f}" for i in range(len(self.names))) for k in moved))
        return "\n".join(lines)


def error_stages(recording, patch: ModelPatch, *, replayer=None, nthread: int = 2) -> Stages:
    """Baseline and the patch's effects added one at a time; see the module docstring."""
    from adadex.sysid.replay import Replayer

    rep = replayer if replayer is not None else Replayer(recording, nthread=nthread)
    names, patches = ["baseline (nominal model)"], [ModelPatch(robot=rep.robot)]
    for e in patch.effects:
        patches.append(ModelPatch(effects=patches[-1].effects + (e,), robot=rep.robot))
        names.append(f"+ {e.effect} on {','.join(e.joints)}")
    comps = [Comparison(recording=recording, patch=p, simulated=rep.simulate(p)) for p in patches]
    return Stages(names=names, patches=patches, comparisons=comps, heldout=heldout_mask(recording))


def _percent(x) -> str:
    """A reduction as a percentage; "—" (train only: no sequence held out) for ``None``."""
    return "— (train only)" if x is None else f"{100 * x:.0f}%"


def _with_units(h: dict) -> tuple[str, str]:
    """A hypothesis' parameters and 95 % intervals as text with units, intervals that reach the bounds
    marked "not identifiable"."""
    eff = get_effect(h["effect"])
    units = {p.name: p.unit for p in eff.params}
    ident = h.get("identifiable") or [True] * len(h["joints"])
    params, cis = [], []
    for name, values in h["params"].items():
        for k, (joint, v) in enumerate(zip(h["joints"], values)):
            params.append(f"{name} = {v:.4g} {units[name]}" + (f" ({joint})" if len(h["joints"]) > 1 else ""))
            a, b = h["ci95"][name][k]
            cis.append(f"[{a:.4g}, {b:.4g}] {units[name]}" + ("" if ident[k] else " — not identifiable"))
    return "; ".join(params), "; ".join(cis)


def _hypothesis_table(hypotheses: list[dict]) -> str:
    """The diagnosis' hypotheses as an HTML table: effect, joints, parameters and 95 % intervals with units,
    train and held-out reductions, the cost they were scored on (``scored_by``: ``windowed``, 0.25-s windows
    restarted from the measured positions, or ``replay``, a free replay; "—" in a diagnosis written before
    it) and the look-alike alternatives."""
    rows = ["<table><tr><th class='l'>effect</th><th class='l'>joints</th><th class='l'>parameters</th>"
            "<th class='l'>95% CI</th><th>train reduction</th><th>held-out reduction</th>"
            "<th class='l'>scored by</th><th class='l'>alternatives</th></tr>"]
    for h in hypotheses:
        params, cis = _with_units(h)
        rows.append(f"<tr><td class='l'>{h['effect']}</td><td class='l'>{','.join(h['joints'])}</td>"
                    f"<td class='l'>{html.escape(params)}</td><td class='l'>{html.escape(cis)}</td>"
                    f"<td>{100 * h['train_error_reduction']:.0f}%</td><td>{_percent(h['heldout_error_reduction'])}</td>"
                    f"<td class='l'>{html.escape(str(h.get('scored_by', '—')))}</td>"
                    f"<td class='l'>{', '.join(h['alternatives'])}</td></tr>")
    return "".join(rows) + "</table>"


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


_CSS = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px;text-align:right}
th{background:#f3f3f3}td.l,th.l{text-align:left}img{max-width:100%;margin:0.5em 0}.verdict{font-size:1.3em;font-weight:bold}
code{background:#f3f3f3;padding:1px 4px}"""


def write_report(recording, patch: ModelPatch, out, *, diagnosis=None, title: str = "adadex: model vs measurement",
                 stages: Stages | None = None, nthread: int = 2, max_overlays: int = 6,
                 pd_results: list[dict] | None = None) -> Path:
    """Write the HTML report atomically; returns its path.

    Args:
        recording: the :class:`~adadex.data.recording.Recording` the report is about.
        patch: the :class:`~adadex.sim.patch.ModelPatch` whose effects are added one at a time
            (:func:`error_stages`); the report names it.
        out: the HTML file to write (its folders are created; an existing file is replaced).
        diagnosis: a :class:`~adadex.sysid.diagnose.Diagnosis` to show (its verdict, its 15 best
            hypotheses and its closing findings); None (default): none.
        title: the page's title and heading.
        stages: the :func:`error_stages` of ``recording`` and ``patch``, when already computed; None
            (default): computed here (one replay of the recording per stage).
        nthread: threads of the replay's rollout pool when ``stages`` is None (default 2).
        max_overlays: at most this many joints get an overlay plot (command, measured, model before and
            after), the failing ones first, each on its worst own sequence (default 6).
        pd_results: :func:`~adadex.sysid.fit.identify_pd` results to tabulate; None (default): no table.

    Returns:
        the path of the written file (``out``).
    """
    st = stages if stages is not None else error_stages(recording, patch, nthread=nthread)
    base, final = st.comparisons[0], st.comparisons[-1]
    loc = localize(base)
    joints = list(base.joint_names)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    parts.append(f"<p>{recording.num_sequences} sequences × {recording.num_steps} samples at "
                 f"{1 / recording.dt:.0f} Hz on joints <code>{html.escape(', '.join(joints))}</code>. "
                 f"Patch: <code>{html.escape(patch.describe())}</code></p>")
    if diagnosis is not None:
        parts.append(f"<p class='verdict'>Diagnosis: {html.escape(diagnosis.verdict)}</p>")
    parts.append("<h2>The error falls</h2><table><tr><th class='l'>stage</th><th>train RMS (deg)</th>"
                 "<th>held-out RMS (deg)</th></tr>")
    for i, n in enumerate(st.names):
        parts.append(f"<tr><td class='l'>{html.escape(n)}</td><td>{np.degrees(st.overall('train')[i]):.3f}</td>"
                     f"<td>{np.degrees(st.overall('heldout')[i]):.3f}</td></tr>")
    parts.append("</table>")
    for split in ("train", "heldout"):
        parts.append(_img(plots.fig_to_png(plots.error_fall(st.names, st.per_joint(split), joints, split)),
                          f"error per joint by stage, {split}"))
    parts.append("<h2>Where the nominal model fails</h2><ul>")
    parts += [f"<li>{html.escape(s)}</li>" for s in loc.sentences]
    parts.append("</ul>")
    if diagnosis is not None:
        parts.append("<h2>Diagnosis: candidate effects, best first</h2>" + _hypothesis_table(diagnosis.hypotheses[:15]))
        parts.append("<ul>" + "".join(f"<li>{html.escape(f)}</li>" for f in diagnosis.findings[-len(diagnosis.explained_fraction) - 1:]) + "</ul>")
    if pd_results:
        parts.append("<h2>The paper's identification: per-joint servo gains, CMA-ES vs least squares</h2>"
                     "<p>kp and kd scales fitted alone (no other effect) to Σ‖q<sub>sim</sub> − q<sub>real</sub>‖² "
                     "on each joint's sequences. A gain fit absorbs what it can of other effects; the residual "
                     "MSE shows how much it leaves.</p><table><tr><th class='l'>joint</th><th class='l'>method</th>"
                     "<th>kp scale</th><th>kd scale</th><th>MSE nominal (rad²)</th><th>MSE fitted (rad²)</th>"
                     "<th>evaluations</th><th>seconds</th></tr>")
        for r in pd_results:
            parts.append(f"<tr><td class='l'>{r['joint']}</td><td class='l'>{r['method']}</td><td>{r['kp_scale']:.3f}</td>"
                         f"<td>{r['kd_scale']:.3f}</td><td>{r['mse_nominal']:.2e}</td><td>{r['mse']:.2e}"
                         f"{'' if r.get('progress', True) else ' (no progress: nominal kept)'}</td>"
                         f"<td>{r['evaluations']}</td><td>{r['seconds']:.1f}</td></tr>")
        parts.append("</table>")
    parts.append("<h2>Overlays: command, measured, model before and after</h2>")
    err = base.rms_per_sequence_joint()
    # Each failing joint (then the others, worst first) on its own worst sequence: the one that moves it.
    seqs = list(recording.meta.get("sequences") or [{} for _ in range(recording.num_sequences)])
    order = loc.failing_joints + [e["joint"] for e in loc.joints if e["joint"] not in loc.failing_joints]
    sims = {"model (nominal)": base.simulated, "model + patch": final.simulated}
    for name in order[:max_overlays]:
        j = joints.index(name)
        own = np.array([s.get("joint", name) == name for s in seqs])
        own = own if own.any() else np.ones(len(seqs), dtype=bool)
        s = int(np.flatnonzero(own)[np.argmax(err[own, j])])
        parts.append(_img(plots.fig_to_png(plots.overlay(recording, sims, s, name)), f"overlay {name}"))
    vmax = float(np.degrees(err.max())) or None
    parts.append("<h2>Error by joint and sequence</h2>")
    parts.append(_img(plots.fig_to_png(plots.heatmap(err, joints, recording.sequence_labels, "nominal model", vmax)), "heatmap before"))
    parts.append(_img(plots.fig_to_png(plots.heatmap(final.rms_per_sequence_joint(), joints, recording.sequence_labels,
                                                     "model + patch", vmax)), "heatmap after"))
    parts.append("</body></html>")
    return atomic_write_text(out, "\n".join(parts))
