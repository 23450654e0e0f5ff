"""Latent smoothness (paper D.1): how much a policy's action moves when the object latent moves.

For sampled observations x and random latent perturbations δ of norm ε,

    ρ(x, δ) = ‖a(x with latent f + δ) − a(x)‖ / ε,

with the policy's deterministic action. A tracker whose ρ is small and concentrated responds
smoothly to the latent, which is what makes the O channel (a continuous modulated latent) usable;
large or heavy-tailed ρ means small latent edits flip behaviour. :func:`latent_smoothness` returns
the distribution, :func:`plot_latent_smoothness` draws it (the paper's Fig. 12 style: histogram
and CDF, one curve per policy).

Example
-------
>>> import torch
>>> from tensordict import TensorDict
>>> from adadex.modules.tracker import Tracker
>>> obs = TensorDict({"observation": torch.randn(16, 273)}, batch_size=[16])
>>> out = latent_smoothness(Tracker(hidden=(32, 32)), obs, eps=0.05, perturbations=4, seed=0)
>>> out["rho"].shape
torch.Size([64])
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.envs.observation import LAYOUT, OBJECT_LATENT, OBSERVATION
from adadex.errors import ConfigError, UnknownKeyError
from adadex.io import atomic_write


def latent_smoothness(policy, observations: TensorDictBase, *, eps: float = 0.05, perturbations: int = 8,
                      seed: int = 0, action_key="action") -> dict:
    """ρ for every observation × perturbation (see the module docstring).

    Args:
        policy: a TensorDictModule reading ``"observation"`` (e.g. a tracker's actor).
        observations: a TensorDict of any batch shape holding ``"observation"`` (273-D) and whatever
            else the policy reads (``("object", "latent")``, a residual tracker's joint targets); the
            flat and the structured latent are perturbed alike.
        eps: the perturbation norm (latents live in (−1, 1)).
        perturbations: random directions per observation.
        seed: seeds the directions.
        action_key: the policy's output compared (default ``"action"``).

    Returns ``{"rho": (N·P,) tensor, "mean", "median", "p95", "max", "eps"}``.
    """
    if not eps > 0 or perturbations < 1:
        raise ConfigError(f"need eps > 0 and perturbations ≥ 1, got eps={eps}, perturbations={perturbations}")
    if OBSERVATION not in observations.keys():
        raise UnknownKeyError("observations must hold the flat 'observation' entry")
    reads = dict.fromkeys([OBSERVATION, OBJECT_LATENT, *getattr(policy, "in_keys", ())])
    base = observations.reshape(-1).select(*[k for k in reads if k in observations.keys(True)]).clone()
    n = base.batch_size[0]
    g = torch.Generator().manual_seed(seed)
    delta = torch.randn(perturbations, n, LAYOUT["latent"].stop - LAYOUT["latent"].start, generator=g)
    delta = eps * delta / torch.linalg.vector_norm(delta, dim=-1, keepdim=True)
    moved = base.expand(perturbations, n).clone()
    moved[OBSERVATION][..., LAYOUT["latent"]] += delta.to(moved[OBSERVATION].dtype)
    if OBJECT_LATENT in moved.keys(True):
        moved.set(OBJECT_LATENT, moved.get(OBJECT_LATENT) + delta)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        a0 = policy(base.clone()).get(action_key)
        a1 = policy(moved.reshape(-1)).get(action_key).reshape(perturbations, n, -1)
    rho = (torch.linalg.vector_norm(a1 - a0[None], dim=-1) / eps).reshape(-1)
    return {"rho": rho, "mean": float(rho.mean()), "median": float(rho.median()),
            "p95": float(torch.quantile(rho, 0.95)), "max": float(rho.max()), "eps": eps}


def plot_latent_smoothness(results: dict[str, dict], path) -> None:
    """Histogram and CDF of ρ, one curve per named result (``{name: latent_smoothness(...)}``), as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_h, ax_c) = plt.subplots(1, 2, figsize=(10, 4))
    for name, res in results.items():
        rho = res["rho"].double().numpy()
        ax_h.hist(rho, bins=40, alpha=0.5, density=True, label=f"{name} (median {res['median']:.2f})")
        xs = sorted(rho)
        ax_c.plot(xs, [(i + 1) / len(xs) for i in range(len(xs))], label=name)
    ax_h.set_xlabel("ρ = ‖Δa‖ / ε  (rad per unit latent)")
    ax_h.set_ylabel("density")
    ax_h.set_title("latent smoothness")
    ax_h.legend()
    ax_c.set_xlabel("ρ")
    ax_c.set_ylabel("fraction ≤ ρ")
    ax_c.grid(alpha=0.3)
    eps = {res["eps"] for res in results.values()}
    fig.suptitle(f"action change per latent perturbation (ε = {', '.join(f'{e:g}' for e in sorted(eps))})")
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)
