"""What a hidden robot costs kinematic replay, and how much of it a fixed arm gain takes back: the screen
that chooses the sim-to-real gap presets (``assets/gaps/``, docs/sim2real.md).

Every candidate robot (a model patch file, or effects given inline as JSON) runs replay on the same
episodes — the unseen-trajectory test references × ``--repeats`` Table 3 draws, env seed 20000, as the
presets' table — once as it is and once per ``--gains`` value with channel K's edit held fixed: the
arm's action gains ``clip(g · (q_ref,t − q_t), ±0.1 rad)`` (``GainModulation`` with the arm's gain
latched at g, the hand's at 0, or at h for a value ``g:h``; a negative gain softens the servos to
kp × (1 + g), ``ModulationConfig.max_softening``). A gap that costs ≥ 10 completion points and that a fixed gain takes
back is one a K modulator can learn to recover; one that no gain moves (a servo saturated against a
torque limit, a spring or a load too heavy for it) is not.

    python benchmarks/gap_screen.py --dataset data/small_pg --patch assets/gaps/heavy_soft_arm.json
    python benchmarks/gap_screen.py --dataset data/small_pg --gains 0:-0.55,0:-0.3 --repeats 4   # a softer grip
    python benchmarks/gap_screen.py --dataset data/small_pg --gains 1,2 \\
        --effects '{"spring": [{"effect": "joint_spring", "joints": ["arm_j2", "arm_j3"], "params": {"stiffness": 30}}]}'
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from _data import result_arguments, write_result

FIELDS = ("completion_pct", "object_completion_pct", "T_o")


def fixed_arm_gain(gain: float, bound: float = 0.1, hand: float = 0.0):
    """A module adding channel K's edit with the arm's gain held at ``gain`` (the hand's at ``hand``) to a
    policy's action."""
    import torch
    from tensordict.nn import TensorDictModule

    from adadex.envs.observation import JOINT_POS, REF_JOINT_POS

    class _Gain(torch.nn.Module):
        def forward(self, action, q, ref):
            g = torch.full((action.shape[-1],), hand, dtype=action.dtype)
            g[:6] = gain
            return action + (g * (ref[..., 0, :] - q)).clamp(-bound, bound)

    return TensorDictModule(_Gain(), ["action", JOINT_POS, REF_JOINT_POS], ["action"])


def _gain(text: str) -> tuple[float, float]:
    """``"1"`` → (1, 0); ``"1:-0.5"`` → (1, −0.5): the arm's gain and the hand's."""
    from adadex.errors import ConfigError

    try:
        arm, _, hand = text.strip().partition(":")
        return float(arm), float(hand or 0.0)
    except ValueError:
        raise ConfigError(f"--gains: {text!r} is not a gain (G or ARM:HAND, e.g. 1 or 1:-0.5)") from None


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, required=True)
    p.add_argument("--patch", type=Path, action="append", default=[], help="a hidden robot's patch file (repeatable)")
    p.add_argument("--effects", default=None, help='JSON {"name": [effect, …]}: robots given inline')
    p.add_argument("--gains", default="1,2", help="fixed arm gains to try, comma-separated (default 1,2); "
                   "ARM:HAND also sets the hand's")
    p.add_argument("--repeats", type=int, default=2, help="Table 3 draws per test reference (default 2)")
    a = result_arguments(p, "gap_screen")(argv)

    from tensordict.nn import TensorDictSequential

    from adadex.data.reference import ReferenceDataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import TrackingConfig, episode_references
    from adadex.errors import ConfigError
    from adadex.eval.evaluate import evaluate
    from adadex.modules.tracker import Tracker
    from adadex.sim.patch import ModelPatch
    from adadex.transforms.policy import make_policy

    robots = {"nominal": None, **{f.stem: ModelPatch.load(f) for f in a.patch}}
    if a.effects:
        try:
            inline = json.loads(a.effects)
        except json.JSONDecodeError as e:
            raise ConfigError(f"--effects: not JSON ({e})") from None
        robots.update({k: ModelPatch.from_dict({"version": 1, "model": "builtin", "effects": v}, source=f"--effects {k}")
                       for k, v in inline.items()})
    gains = [_gain(g) for g in a.gains.split(",") if g.strip()]
    ds = ReferenceDataset(a.dataset)
    refs = episode_references(ds, ("unseen_trajectory", "test"), 300) * a.repeats
    rows = {}
    for name, patch in robots.items():
        for g in [(0.0, 0.0), *gains]:
            policy = make_policy(Tracker.replay().freeze(), None, channels="none")
            if any(g):
                policy = TensorDictSequential(policy, fixed_arm_gain(g[0], hand=g[1]))
            r = evaluate(policy, ds, split=None, references=refs, config=TrackingConfig(window=300),
                         randomize=Randomization(), seed=20_000, progress=False, nthread=2,
                         **({"patch": patch} if patch is not None else {}))
            label = f"{g[0]:g}" + (f":{g[1]:g}" if g[1] else "")
            rows[f"{name} g={label}"] = {k: r["summary"][k] for k in FIELDS}
            print(f"{name:28s} arm gain {label}: completion {r['summary']['completion_pct']:5.1f} %  object "
                  f"{r['summary']['object_completion_pct']:5.1f} %  T_o {r['summary']['T_o']:.2f} cm", flush=True)
    result = {"dataset": str(a.dataset), "episodes": len(refs), "env_seed": 20_000,
              "gains": [g[0] if not g[1] else list(g) for g in gains],
              "robots": {k: (v.to_dict() if v is not None else None) for k, v in robots.items()}, "rows": rows}
    write_result(a.out, result, name="gap_screen", force=a.force, indent=1)
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    from adadex.errors import exit_on_error

    with exit_on_error("benchmarks/gap_screen.py"):
        main()
