"""What the workbench tells the user: parameters it cannot pin down are flagged with the excitation that
would, the CMA-ES comparison never ends worse than the model it started from, the report gives units,
and the error heatmap's log scale keeps small failures visible."""

import numpy as np
import pytest

from adadex.sim.effects import get_effect
from adadex.sim.patch import ModelPatch
from adadex.sysid.diagnose import Candidate, _describe, identifiable
from adadex.sysid.excite import design_excitation, simulate_recording
from adadex.sysid.fit import identify_pd, sequences_moving
from adadex.sysid.replay import Replayer
from adadex.sysid.report import _with_units


def _bounds(effect, joint):
    lo, hi = get_effect(effect).bounds([joint], None)
    return float(lo[0, 0]), float(hi[0, 0])


def test_an_interval_that_spans_the_bounds_is_not_identifiable_and_says_which_excitation_would_pin_it():
    lo, hi = _bounds("payload_mass", "arm_j6")
    assert not identifiable("payload_mass", "arm_j6", (lo, hi))            # the whole range: a flat error
    assert not identifiable("payload_mass", "arm_j6", (0.5 * (lo + hi), hi))   # reaches the upper bound
    mid = 0.3 * lo + 0.7 * hi
    assert identifiable("payload_mass", "arm_j6", (0.98 * mid, 1.02 * mid))
    flat = Candidate(effect="coulomb_friction", joint="if_pip", value=0.2, ci95=_bounds("coulomb_friction", "if_pip"),
                     train_error_reduction=0.5, heldout_error_reduction=0.5, score=0.5)
    text = _describe(flat, None)
    assert "not identifiable from this recording" in text
    assert "adadex sysid excite --joints if_pip --freqs 0.25,0.5" in text
    pinned = Candidate(effect="coulomb_friction", joint="if_pip", value=0.2, ci95=(0.19, 0.21),
                       train_error_reduction=0.5, heldout_error_reduction=0.5, score=0.5)
    assert "not identifiable" not in _describe(pinned, None) and "N·m" in _describe(pinned, None)


def test_report_parameters_carry_units_and_flag_unpinned_intervals():
    h = {"effect": "payload_mass", "joints": ["arm_j6"], "params": {"mass": [1.02]},
         "ci95": {"mass": [[0.98, 1.06]]}, "identifiable": [True]}
    params, cis = _with_units(h)
    assert params == "mass = 1.02 kg" and cis == "[0.98, 1.06] kg"
    h2 = {"effect": "actuator_delay", "joints": ["if_pip", "mf_pip"], "params": {"delay": [0.05, 0.05]},
          "ci95": {"delay": [[0.049, 0.051], [0.0, 0.2]]}, "identifiable": [True, False]}
    params, cis = _with_units(h2)
    assert "delay = 0.05 s (if_pip)" in params and "(mf_pip)" in params
    assert cis.count("not identifiable") == 1 and cis.endswith("— not identifiable")


@pytest.fixture(scope="module")
def nominal_recording():
    plan = design_excitation(["arm_j5"], freqs=(1.0,), amps=(0.5,), poses=("loaded",), kinds=("sine",), duration=1.5)
    return simulate_recording(plan, ModelPatch(), noise=2e-4, seed=0)


def test_cma_never_returns_worse_than_the_start_and_says_when_it_made_no_progress(nominal_recording):
    rec = nominal_recording
    rep = Replayer(rec, nthread=1)
    r = identify_pd(rep, "arm_j5", sequences_moving(rec, "arm_j5"), method="cma", max_evals=24, seed=0)
    # the data were made on the nominal model: only noise is left, the start is (near) the optimum
    assert r["mse"] <= r["mse_nominal"]
    if not r["progress"]:
        assert (r["kp_scale"], r["kd_scale"]) == (1.0, 1.0) and r["mse"] == r["mse_nominal"]
    # a gain change is real progress, found from the same start
    truth = ModelPatch().with_effect("kp_scale", ["arm_j5"], 0.6)
    plan = design_excitation(["arm_j5"], freqs=(1.0,), amps=(0.5,), poses=("loaded",), kinds=("sine",), duration=1.5)
    rec2 = simulate_recording(plan, truth, noise=2e-4, seed=0)
    r2 = identify_pd(Replayer(rec2, nthread=1), "arm_j5", sequences_moving(rec2, "arm_j5"), method="cma",
                     max_evals=48, seed=0)
    assert r2["progress"] and r2["mse"] < 0.5 * r2["mse_nominal"]


def test_heatmap_log_scale_shows_a_small_failure_beside_a_large_one():
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.colors import LogNorm

    from adadex.sysid.plots import heatmap

    rms = np.radians(np.array([[5.0, 0.05], [4.0, 0.04]]))      # 5° and 0.05°: two decades apart
    fig = heatmap(rms, ["arm_j2", "if_pip"], ["s0", "s1"], "t")
    im = fig.axes[0].images[0]
    assert isinstance(im.norm, LogNorm)
    small = im.norm(0.05)
    assert 0.2 < small < 0.9          # a linear scale would put it at 0.01 of the colour range
    import matplotlib.pyplot as plt

    plt.close(fig)
