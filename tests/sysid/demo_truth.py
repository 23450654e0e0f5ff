"""How ``assets/recordings/demo.npz`` was made, and the effects hidden in it.

Only the tests read this: the demo and the workbench must find the effects on their own.
Regenerate with ``python tests/sysid/demo_truth.py``.
"""

from adadex.resources import asset
from adadex.sim.patch import ModelPatch
from adadex.sysid.excite import design_excitation, simulate_recording

DEMO = asset("recordings", "demo.npz")
JOINTS = ["arm_j2", "arm_j5", "if_mcp", "if_pip", "mf_pip", "th_mcp"]
TRUTH = (ModelPatch()
         .with_effect("coulomb_friction", ["if_pip"], 0.06)
         .with_effect("actuator_delay", ["arm_j2"], 0.025))
NOISE, SEED = 2e-4, 7


def make_demo_recording():
    plan = design_excitation(JOINTS, freqs=(0.5, 2.0), amps=(0.3, 1.0), duration=2.0, rate=60.0)
    return simulate_recording(plan, TRUTH, noise=NOISE, seed=SEED)


if __name__ == "__main__":
    print(make_demo_recording().save(DEMO))
