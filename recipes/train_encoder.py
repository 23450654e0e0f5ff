"""Train the point-cloud encoder (object latent) with Hydra: a thin wrapper of ``adadex.train.encoder``.

    python recipes/train_encoder.py                       # the shipped checkpoint's settings
    python recipes/train_encoder.py steps=50 out=/tmp/enc # a quick run

Writes ``encoder.pt``, ``encoder.json`` (metrics) and ``reconstructions.png`` to ``out``; the same
as ``adadex encoder train``. An ``out`` holding anything but an earlier ``train_encoder.py`` output (its
marker) is refused before any work, nothing written, not even Hydra's ``.hydra/`` (``force=true``
writes into it); an earlier output is replaced.
"""

from __future__ import annotations


import hydra
import torch
from omegaconf import DictConfig

from adadex.errors import exit_on_error
from adadex.train.encoder import save_training_run, train_encoder
from adadex.train.recipe import (
    ENCODER_TRAINING,
    check_keys,
    check_recipe_out,
    claim_recipe_out,
    recipe_main,
)


def guard(cfg) -> None:
    """The output guard, before Hydra starts (nothing written when refused)."""
    check_recipe_out(cfg, ENCODER_TRAINING)


def keys() -> dict:
    """What the recipe accepts: the ``adadex_encoder`` node's keys (:func:`adadex.train.config_store.encoder_node`)."""
    from adadex.train.config_store import keys as node_keys

    return node_keys("adadex_encoder")


@hydra.main(config_path=".", config_name="encoder", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    with exit_on_error("recipes/train_encoder.py"):      # input errors: one line, exit code 2
        check_keys(cfg, keys())
        claim_recipe_out(cfg, ENCODER_TRAINING)        # someone else's folder: refused, before any work
        if cfg.threads:
            torch.set_num_threads(int(cfg.threads))
        model, history = train_encoder(steps=int(cfg.steps), batch_size=int(cfg.batch_size), points=int(cfg.points),
                                       lr=float(cfg.lr), seed=int(cfg.seed))
        save_training_run(cfg.out, model, history)
    final = history["final"]
    print(f"trained in {history['seconds']:.0f} s; Chamfer "
          + "; ".join(f"{k} {v['chamfer_cm2']:.4f} cm² (RMS {v['rms_mm']:.2f} mm)" for k, v in final.items())
          + f"; wrote {cfg.out}")
    return final


if __name__ == "__main__":
    recipe_main(main, schema=keys(), guard=guard, config_name="encoder")
