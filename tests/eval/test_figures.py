"""The figure data (object paths, the latents the tracker saw) read from real evaluation rollouts, and
the plots' output and input checks."""

import json
import shutil

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential

from adadex.data.reference import ReferenceDataset
from adadex.envs.latent import SHIPPED_ENCODER
from adadex.envs.observation import LAYOUT
from adadex.envs.replay import replay_policy
from adadex.envs.tracking import TrackingConfig
from adadex.errors import AdadexError, ConfigError
from adadex.eval.evaluate import evaluate
from adadex.eval.figures import ROW_LABELS, ROWS, channel_usage, decoded_latents, object_paths, plot_ablation, \
    plot_channel_usage, plot_data_scaling, plot_latent_decoding, plot_object_paths
from adadex.modules.channels import ModulationLayout
from adadex.modules.encoder import load_encoder
from adadex.modules.modulator import Modulator
from adadex.modules.nets import GaussianHeads
from adadex.modules.tracker import Tracker
from adadex.transforms.policy import make_policy

CFG = TrackingConfig(window=24)
REFS = [1, 3, 5]          # two chunks of max_worlds=2: [1, 3] and [5]
STARTS = {1: 60, 3: 0, 5: 100}


@pytest.fixture(scope="module")
def shifted(tiny_dataset, tmp_path_factory):
    """A copy of the tiny dataset whose episodes start later in some references (window_start ≠ 0)."""
    out = tmp_path_factory.mktemp("shifted") / "tiny"
    shutil.copytree(tiny_dataset, out)
    index = json.loads((out / "index.json").read_text())
    for i, start in STARTS.items():
        index["references"][i]["window_start"] = start
    (out / "index.json").write_text(json.dumps(index))
    return out


@pytest.fixture(scope="module")
def replay(shifted):
    return evaluate(replay_policy(), shifted, split=None, references=REFS, max_worlds=2, config=CFG,
                    keep_rollouts=True, progress=False)


@pytest.fixture(scope="module")
def modulated(shifted):
    """R+O+T on an untrained tracker, with the modulator's heads scaled up so that its deterministic
    action is far from zero; ``seen`` records every observation the tracker read."""
    torch.manual_seed(0)
    tracker = Tracker(hidden=(32, 32))
    # the tracker's observation alone: the scene below (world 0 falls early) is this seed's draw
    modulator = Modulator("R+O+T", hidden=(32, 32), init_scale=1.0, inputs="observation")
    for heads in (m for m in modulator.modules() if isinstance(m, GaussianHeads)):
        for h in heads.heads:
            h.weight.data.mul_(300)
    seen = []
    spy = TensorDictModule(lambda obs: seen.append(obs.clone()) or obs[..., :1], in_keys=["observation"],
                           out_keys=[("spy", "x")])
    policy = make_policy(TensorDictSequential(spy, tracker.actor), modulator, channels="R+O+T")
    res = evaluate(policy, shifted, split=None, references=REFS, max_worlds=2, config=CFG,
                   env_transform=policy.primer, keep_rollouts=True, progress=False)
    return res, seen


def test_original_path_is_the_reference_the_env_showed(replay, shifted):
    ds = ReferenceDataset(shifted)
    for chunk, refs in ((0, REFS[:2]), (1, REFS[2:])):
        td = replay["rollouts"][chunk]
        for w, ref in enumerate(refs):
            p = object_paths(td, ds, refs, w)
            assert {k: v.shape for k, v in p.items()} == {k: (CFG.window - 1, 3) for k in p}
            shown = td["reference", "object_pose"][w, :, 0, :3].double().numpy()
            np.testing.assert_array_equal(p["original"], shown)
            np.testing.assert_array_equal(p["modulated"], p["original"])       # nothing modulates replay
            assert np.abs(p["executed"] - p["original"]).max() > 1e-3           # physics is not the reference
            e = ds.entries[ref]
            unshifted = ds.frames["object_pose"][e["offset"]:e["offset"] + CFG.window - 1, :3].double().numpy()
            assert (STARTS[ref] == 0) == np.array_equal(p["original"], unshifted)


def test_paths_stop_at_the_first_done(replay, shifted):
    td = replay["rollouts"][0].clone()
    td["next", "done"][1, 9] = True
    assert len(object_paths(td, shifted, REFS[:2], 1)["executed"]) == 10
    assert len(object_paths(td, shifted, REFS[:2], 0)["executed"]) == CFG.window - 1
    frames, latents = decoded_latents(td, 1, steps=4)
    assert frames == [0, 3, 6, 9] and latents.shape == (4, 64)


def test_object_paths_refuse_a_wrong_chunk(replay, shifted):
    td = replay["rollouts"][0]
    with pytest.raises(ConfigError, match="tracks reference 1"):
        object_paths(td, shifted, [3, 1], 0)
    with pytest.raises(ConfigError, match="2 dataset indices"):
        object_paths(td, shifted, REFS, 0)
    with pytest.raises(ConfigError, match="world"):
        object_paths(td, shifted, REFS[:2], 2)


def test_modulated_paths_and_latents_are_what_the_tracker_saw(modulated, shifted):
    res, seen = modulated
    td = res["rollouts"][0]
    steps = CFG.window - 1
    lengths = []
    for w in range(2):
        p = object_paths(td, shifted, REFS[:2], w)
        n = len(p["original"])
        lengths.append(n)
        assert n == int(td["next", "done"][w].flatten().float().argmax()) + 1
        assert np.abs(p["modulated"] - p["original"]).max() > 5e-3            # R moved the reference
        frames, latents = decoded_latents(td, w, steps=5)
        assert frames == [round(f) for f in np.linspace(0, n - 1, 5)]
        assert (latents - td["object", "latent"][w, 0]).abs().max() > 0.05     # O moved the latent
        for i, f in enumerate(frames):
            obs = seen[f][w]          # the first chunk's tracker calls come first, one per step
            torch.testing.assert_close(obs[LAYOUT["latent"]], latents[i], rtol=0, atol=0)
            ref_now = (obs[LAYOUT["object_pose"]][:3] - obs[LAYOUT["object_error"]][:3]).double().numpy()
            np.testing.assert_allclose(ref_now, p["modulated"][f], atol=1e-6)
    assert len(seen) == 2 * steps
    assert lengths[0] < steps == lengths[1], "world 0 should fall early (the object drifts off) and world 1 not"


def test_unmodulated_latents_are_the_env_latent(replay):
    td = replay["rollouts"][0]
    frames, latents = decoded_latents(td, 0, steps=3)
    assert frames == [0, 11, 22]
    torch.testing.assert_close(latents, td["object", "latent"][0, frames])
    with pytest.raises(ConfigError, match="steps"):
        decoded_latents(td, 0, steps=CFG.window)
    with pytest.raises(ConfigError, match="channels"):
        decoded_latents(td.clone().set(("modulation", "sample"), torch.zeros(*td.batch_size, 198)), 0,
                        channels="R+T")


def _png(path):
    assert path.is_file() and path.stat().st_size > 1000
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plots_from_a_modulated_rollout(modulated, shifted, tmp_path):
    res, _ = modulated
    td = res["rollouts"][0]
    p = object_paths(td, shifted, REFS[:2], 0)
    assert _png(plot_object_paths(p, tmp_path / "paths.png", title="bottle"))
    frames, latents = decoded_latents(td, 0, steps=3)
    model = load_encoder(SHIPPED_ENCODER)[0]
    obj = ReferenceDataset(shifted).entries[REFS[0]]["object"]
    out = plot_latent_decoding(model, latents, frames, obj, tmp_path / "latents.png",
                               original_latent=td["object", "latent"][0, 0])
    assert _png(out)

    bad = dict(p, executed=p["executed"][:-1])
    with pytest.raises(ConfigError, match="executed"):
        plot_object_paths(bad, tmp_path / "x.png")
    nan = {k: v.copy() for k, v in p.items()}
    nan["modulated"][4, 1] = np.nan
    with pytest.raises(ConfigError, match="modulated.*frame 4"):
        plot_object_paths(nan, tmp_path / "x.png")
    with pytest.raises(ConfigError, match="latents"):
        plot_latent_decoding(model, latents[:, :10], frames, obj, tmp_path / "x.png")
    with pytest.raises(ConfigError, match="frames"):
        plot_latent_decoding(model, latents, frames[:2], obj, tmp_path / "x.png")
    with pytest.raises(AdadexError, match="cylinder"):
        plot_latent_decoding(model, latents, frames, "cylinderr_02", tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def _cell(values, ci=True):
    return {r: {"completion_pct": v, "completion_pct_ci95": [v - 5, v + 5] if ci else None,
                "mean_error_pct": v / 2, "mean_error_pct_ci95": None} for r, v in values.items()}


def test_ablation_plot(tmp_path):
    full = {s: {c: _cell({r: 10.0 + 10 * i for i, r in enumerate(ROWS)}) for c in ("nominal", "randomized")}
            for s in ("unseen_trajectory", "unseen_object")}
    assert _png(plot_ablation(full, tmp_path / "full.png"))
    assert _png(plot_ablation(full, tmp_path / "mean.png", metric="mean_error_pct"))
    partial = {"unseen_object": {"randomized": _cell({"tracker": 40.0, "ROT": 55.0}, ci=False)}}
    assert _png(plot_ablation(partial, tmp_path / "partial.png"))
    assert set(ROW_LABELS) == set(ROWS)

    for table, match in (({}, "non-empty"), ({"unseen_scene": {}}, "unknown split"),
                         ({"unseen_object": {"noisy": {}}}, "unknown condition"),
                         ({"unseen_object": {"nominal": _cell({"dagger": 1.0})}}, "unknown row 'dagger'"),
                         ({"unseen_object": {"nominal": {}}}, "no row"),
                         ({"unseen_object": {"nominal": _cell({"R": float("nan")})}},
                          r"\['unseen_object'\]\['nominal'\]\['R'\]\['completion_pct'\] must be finite"),
                         ({"unseen_object": {"nominal": {"R": {"completion_pct": 1.0,
                                                               "completion_pct_ci95": [3.0, 2.0]}}}}, "lo > hi")):
        with pytest.raises(ConfigError, match=match):
            plot_ablation(table, tmp_path / "bad.png")
    with pytest.raises(ConfigError, match="no 'T_x' entry"):
        plot_ablation(full, tmp_path / "bad.png", metric="T_x")
    assert not (tmp_path / "bad.png").exists()


def test_data_scaling_plot(tmp_path):
    fractions = [0.1, 0.25, 0.5, 1.0]
    results = {"tracker": [(20.0, 15.0, 25.0), (35.0, None, None), (50.0, 44.0, 56.0), (60.0, 55.0, 66.0)],
               "+R+O+T": [(30.0, None, None)] * 4}
    assert _png(plot_data_scaling(fractions, results, tmp_path / "scaling.png", title="unseen objects"))
    for f, r, match in ((fractions, {"t": results["tracker"][:3]}, "3 points for 4 fractions"),
                        ([0.0, 1.0], {"t": [(1.0, None, None)] * 2}, "> 0"),
                        ([], {}, "non-empty"),
                        (fractions, {"t": [(1.0, None, 2.0)] * 4}, "both lo and hi"),
                        (fractions, {"t": [(float("nan"), None, None)] * 4},
                         r"results\['t'\]\[0\] mean must be finite"),
                        (fractions, {"t": [(1.0, 2.0, 0.0)] * 4}, "lo > hi")):
        with pytest.raises(ConfigError, match=match):
            plot_data_scaling(f, r, tmp_path / "bad.png")


def test_channel_usage_reads_the_modulator_action_of_each_entry(modulated, tmp_path):
    res, _ = modulated
    usage = channel_usage(res["rollouts"], "R+O+T")
    assert set(usage) == {"ref_hand", "ref_object", "latent", "action"}, usage
    assert all(0.0 < v <= 1.0 for v in usage.values()), usage
    # the latent entry by hand: its slice of the flat action, frames up to each world's first done
    sl = next(sl for key, sl, _ in ModulationLayout("R+O+T").segments if key[-1] == "latent")
    total, frames = 0.0, 0
    for td in res["rollouts"]:
        for w in range(td.batch_size[0]):
            n = int(td["next", "done"][w].reshape(-1).int().argmax()) + 1 if td["next", "done"][w].any() \
                else td.batch_size[1]
            total += float(td["modulation", "sample"][w, :n, sl].abs().mean(-1).sum())
            frames += n
    assert usage["latent"] == pytest.approx(total / frames, rel=1e-6)
    _png(plot_channel_usage({"ROT": usage, "O": {"latent": 0.0}}, tmp_path / "usage.png"))
    with pytest.raises(ConfigError, match="at least one entry"):
        plot_channel_usage({"ROT": {}}, tmp_path / "bad.png")
    with pytest.raises(ValueError, match="must have"):
        channel_usage(res["rollouts"], "R")
