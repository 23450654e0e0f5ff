"""The Table 1 pipeline's figures (``out/figures/``), made from its table and the first seed's policies:
the ablation bars (completion, and object completion where the evaluations stored it), Fig. 4 (original,
modulated and executed object path), Fig. 5 (the modulated latent decoded against the object), Fig. 6
(data scaling), Fig. 12 (latent smoothness ρ) and how much each modulator uses each of its channels."""

from __future__ import annotations

import json

import numpy as np
import torch

from adadex.envs.latent import SHIPPED_ENCODER, encoder_latent
from adadex.envs.tracking import episode_references
from adadex.eval import figures as fig
from adadex.eval.latent_smoothness import latent_smoothness, plot_latent_smoothness
from adadex.eval.table1 import ROW_LABELS, ci95
from adadex.io import atomic_write_text
from adadex.modules.channels import ModulationConfig
from adadex.modules.encoder import load_encoder
from adadex.modules.tracker import Tracker


def pipeline_figures(p, table: dict, scaling: dict, paths: dict, seed: int, modulator_rows) -> dict[str, str]:
    """The figures of pipeline ``p`` (a :class:`~adadex.train.pipeline.Pipeline` after its run) from
    ``table`` (``table1.json``'s content), ``scaling`` (Fig. 6's summaries by fraction, one per seed),
    ``paths`` (seed ``seed``'s policy checkpoints by row) and ``modulator_rows`` (the modulator rows
    whose channel use is plotted); returns ``{figure: file}``."""
    folder = p.out / "figures"
    out = {"ablation": fig.plot_ablation(table, folder / "ablation.png")}
    entries = [e for by_condition in table.values() for rows in by_condition.values() for e in rows.values()]
    if all(np.isfinite(e.get("object_completion_pct", np.nan)) for e in entries):   # stored before the metric: NaN
        out["ablation_object"] = fig.plot_ablation(table, folder / "ablation_object.png", metric="object_completion_pct")
    # Fig. 4 and 5: the R+O+T policy of the first seed on the unseen-trajectory test references
    refs = episode_references(p.ds, ("unseen_trajectory", "test"), p.env_config.window)[: p.cfg.collector.worlds]
    res = p.evaluate(p.policy("ROT", paths), "unseen_trajectory", "nominal", 20_000 + seed,
                        references=refs, keep_rollouts=True)
    td = res["rollouts"][0]
    paths_xyz = [fig.object_paths(td, p.ds, refs, w) for w in range(len(refs))]
    w = int(np.argmax([np.abs(p["modulated"] - p["original"]).max() for p in paths_xyz]))
    name = p.ds.entries[refs[w]]["name"]
    out["fig4_object_path"] = fig.plot_object_paths(paths_xyz[w], folder / "fig4_object_path.png",
                                                    title=f"{name}: reference, modulated reference, executed")
    frames, latents = fig.decoded_latents(td, w, channels=p.cfg.row_channels("ROT"),
                                          config=ModulationConfig(**p.cfg.modulator.modulation))
    obj = p.ds.entries[refs[w]]["object"]
    out["fig5_latent"] = fig.plot_latent_decoding(load_encoder(SHIPPED_ENCODER)[0], latents, frames, obj,
                                                  folder / "fig5_latent.png",
                                                  original_latent=torch.tensor(encoder_latent(obj)))   # a copy: the cache is read-only
    # Fig. 6: completion against the fraction of references distilled from
    def point(values):
        lo_hi = ci95(values)
        return (float(np.mean(values)), *((max(lo_hi[0], 0.0), min(lo_hi[1], 100.0)) if lo_hi else (None, None)))

    series = {"generalist (unseen trajectory, randomized)":
              [point([s["completion_pct"] for s in scaling[f]]) for f in scaling]}
    out["fig6_scaling"] = fig.plot_data_scaling(list(scaling), series, folder / "fig6_scaling.png")
    # Fig. 12: latent smoothness of the trackers on the observations the generalist met
    actors = {row: Tracker.load(paths[row]).actor for row in ("tracker", "ppo", "il_rl")}
    reads = dict.fromkeys(["observation", ("object", "latent"), *(k for a in actors.values() for k in a.in_keys)])
    obs = torch.cat([t.reshape(-1).select(*reads)
                     for t in p.evaluate(p.policy("tracker", paths), "unseen_trajectory", "nominal",
                                            20_000 + seed, keep_rollouts=True)["rollouts"]])
    pick = torch.randperm(obs.shape[0], generator=torch.Generator().manual_seed(seed))[: p.cfg.evaluation.smoothness_samples]
    rho = {row: latent_smoothness(actor, obs[pick], seed=seed) for row, actor in actors.items()}
    plot_latent_smoothness({ROW_LABELS[k]: v for k, v in rho.items()}, folder / "fig12_smoothness.png")
    out["fig12_smoothness"] = folder / "fig12_smoothness.png"
    # which channels each modulator uses, on the randomized unseen-trajectory episodes: the figures' one
    # costly evaluation (every modulator row's randomized episodes again), so a stage a rerun skips
    def use(row):
        return fig.channel_usage(p.evaluate(p.policy(row, paths), "unseen_trajectory", "randomized", 20_000 + seed,
                                            keep_rollouts=True)["rollouts"], p.cfg.row_channels(row))

    usage = {row: p._stage(p.out / f"seed_{seed}" / "eval" / "channel_usage" / row,
                           {"policy": paths[row], "tracker": paths["tracker"], "repeats": p.cfg.evaluation.repeats,
                            "seed": seed}, lambda row=row: use(row), label=f"seed {seed} channel use of {row}")
             for row in modulator_rows}
    out["channel_usage"] = fig.plot_channel_usage(usage, folder / "channel_usage.png")
    atomic_write_text(folder / "channel_usage.json", json.dumps(usage, indent=1))
    atomic_write_text(folder / "smoothness.json",
                      json.dumps({k: {m: v[m] for m in ("mean", "median", "p95", "max", "eps")}
                                  for k, v in rho.items()}, indent=1))
    return {k: str(v) for k, v in out.items()}
