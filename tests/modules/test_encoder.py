"""The point-cloud encoder (object latent): Chamfer distance, model, training, checkpoints, the
shipped checkpoint, the environment's latent hook and the ``adadex encoder`` command."""

import inspect
import json

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from adadex.cli import main
from adadex.envs.latent import SHIPPED_ENCODER, SHIPPED_LATENTS, EncoderLatents, encoder_latent
from adadex.modules.encoder import (
    EncoderCheckpointError,
    PointCloudAutoencoder,
    PointCloudEncoder,
    chamfer_distance,
    load_encoder,
    object_latents,
    save_encoder,
    save_latents,
)
from adadex.sim.objects import OBJECT_NAMES, get_object, held_out_objects
from adadex.train.encoder import evaluate_encoder, summarize_evaluation, train_encoder, training_objects

QUICK = dict(batch_size=8, points=128, lr=3e-3, progress=False)


def _cloud(name: str, n: int = 512, seed: int = 5) -> torch.Tensor:
    return torch.from_numpy(get_object(name).point_cloud(n, seed=seed))


@pytest.fixture(scope="module")
def quick_run():
    return train_encoder(steps=40, seed=0, **QUICK)


@pytest.fixture(scope="module")
def shipped():
    return load_encoder(SHIPPED_ENCODER)


# ---------------------------------------------------------------------------------- Chamfer


def test_chamfer_hand_computed():
    a = torch.tensor([[[0.0, 0, 0], [2, 0, 0]]])
    b = torch.tensor([[[0.0, 0, 0], [0, 1, 0], [0, 0, 3]]])
    # a→b: 0 and 4 (2,0,0)→(0,0,0); b→a: 0, 1, 9  →  0.5 · (4/2 + 10/3)
    assert torch.allclose(chamfer_distance(a, b), torch.tensor([0.5 * (2.0 + 10.0 / 3.0)]))


def test_chamfer_zero_symmetric_permutation_invariant_and_batched():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(4, 50, 3, generator=g), torch.rand(4, 70, 3, generator=g)
    assert torch.equal(chamfer_distance(a, a), torch.zeros(4))
    assert torch.allclose(chamfer_distance(a, b), chamfer_distance(b, a))
    perm_a, perm_b = torch.randperm(50, generator=g), torch.randperm(70, generator=g)
    assert torch.allclose(chamfer_distance(a[:, perm_a], b[:, perm_b]), chamfer_distance(a, b))
    per_item = torch.cat([chamfer_distance(a[i:i + 1], b[i:i + 1]) for i in range(4)])
    assert torch.allclose(chamfer_distance(a, b), per_item)
    assert (chamfer_distance(a, b) > 0).all()
    with pytest.raises(ValueError, match="expects"):
        chamfer_distance(a[0], b[0])


def test_chamfer_gradient_matches_differentiating_cdist():
    g = torch.Generator().manual_seed(1)
    a0, b = torch.rand(2, 30, 3, generator=g), torch.rand(2, 40, 3, generator=g)
    a = a0.clone().requires_grad_()
    chamfer_distance(a, b).sum().backward()
    ref = a0.clone().requires_grad_()
    d2 = torch.cdist(ref, b).square()
    (0.5 * (d2.amin(2).mean(1) + d2.amin(1).mean(1))).sum().backward()
    assert torch.allclose(a.grad, ref.grad, atol=1e-6)


# ---------------------------------------------------------------------------------- encoder


def test_encoder_module_shapes_bounds_and_invariances():
    torch.manual_seed(0)
    enc = PointCloudEncoder(PointCloudAutoencoder())
    pts = torch.stack([_cloud(n) for n in ("mug_00", "cube_050", "torus_00", "hammer_00", "box_00", "cone_00")])
    td = TensorDict({"object": {"points": pts.reshape(2, 3, 512, 3)}}, batch_size=[2, 3])
    z = enc(td)["object", "latent"]
    assert z.shape == (2, 3, 64) and (z.abs() < 1).all()
    assert enc.in_keys == [("object", "points")] and enc.out_keys == [("object", "latent")]
    ae = enc.autoencoder
    with torch.no_grad():
        flat = ae.encode(pts)
        assert torch.equal(flat.reshape(2, 3, 64), z.detach())
        assert torch.allclose(ae.encode(pts[:, torch.randperm(512)]), flat, atol=1e-6)   # point order
        assert torch.allclose(ae.encode(pts + torch.tensor([0.3, -0.2, 0.1])), flat, atol=1e-5)  # position
        assert not torch.allclose(ae.encode(2 * pts), flat, atol=1e-3)   # size matters: no rescaling
        assert torch.equal(ae.encode(pts), flat)
        assert ae(pts).shape == (6, ae.config.decoded_points, 3)


# ---------------------------------------------------------------------------------- training


def test_training_lowers_the_chamfer_loss(quick_run):
    model, history = quick_run
    assert len(history["loss"]) == 40
    assert history["final"]["train"]["chamfer_cm2"] < 0.5 * history["initial"]["train"]
    assert history["final"]["held_out"]["chamfer_cm2"] < 0.5 * history["initial"]["held_out"]
    assert np.mean(history["loss"][-5:]) < 0.5 * np.mean(history["loss"][:5])
    meta = history["meta"]
    assert meta["objects"] == list(training_objects()) and len(meta["objects"]) == 75
    assert meta["held_out"] == list(held_out_objects()) and meta["steps"] == 40 and meta["seed"] == 0
    assert not model.training


def test_training_is_seeded(quick_run):
    state = torch.get_rng_state()
    a, _ = train_encoder(steps=3, seed=7, **QUICK)
    b, _ = train_encoder(steps=3, seed=7, **QUICK)
    c, _ = train_encoder(steps=3, seed=8, **QUICK)
    assert torch.equal(torch.get_rng_state(), state)          # the global RNG is left alone
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)


def test_training_rejects_bad_settings():
    with pytest.raises(ValueError, match="steps"):
        train_encoder(steps=-1, progress=False)
    with pytest.raises(ValueError, match="batch_size"):
        train_encoder(steps=1, batch_size=0, progress=False)


# ---------------------------------------------------------------------------------- checkpoints


def test_checkpoint_round_trip(quick_run, tmp_path):
    model, history = quick_run
    path = save_encoder(tmp_path / "enc.pt", model, history["meta"])
    loaded, meta = load_encoder(path)
    pts = torch.stack([_cloud("mug_03", 128), _cloud("cube_050", 128)])
    with torch.no_grad():
        assert torch.equal(loaded.encode(pts), model.encode(pts))
    assert loaded.config == model.config
    assert meta["seed"] == 0 and meta["metrics"]["train"] == history["final"]["train"]
    assert [p.name for p in tmp_path.iterdir()] == ["enc.pt"]              # no temporary left behind


def test_bad_checkpoints_fail_clearly(quick_run, tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        load_encoder(tmp_path / "nope.pt")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all")
    with pytest.raises(EncoderCheckpointError, match="garbage.pt"):
        load_encoder(garbage)
    good = save_encoder(tmp_path / "good.pt", quick_run[0], {})
    cut = tmp_path / "cut.pt"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(EncoderCheckpointError, match="cut.pt"):
        load_encoder(cut)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(EncoderCheckpointError, match="other.pt.*not an adadex encoder"):
        load_encoder(other)


# ---------------------------------------------------------------------------------- shipped checkpoint


def test_shipped_checkpoint_is_small_and_documented(shipped):
    assert SHIPPED_ENCODER.stat().st_size < 2 * 2**20
    _, meta = shipped
    assert len(meta["objects"]) == 75 and set(meta["held_out"]) == set(held_out_objects())
    metrics = json.loads(SHIPPED_ENCODER.with_suffix(".json").read_text())
    assert metrics["seed"] == meta["seed"] and metrics["steps"] == meta["steps"]
    assert metrics["metrics"]["held_out"]["chamfer_cm2"] > 0


def test_shipped_latents_are_distinct_and_shape_aware(shipped):
    model, _ = shipped
    with torch.no_grad():
        z = {n: model.encode(_cloud(n)).numpy() for n in OBJECT_NAMES}
    mat = np.stack(list(z.values()))
    d = np.linalg.norm(mat[:, None] - mat[None], axis=-1)
    assert d[~np.eye(len(mat), dtype=bool)].min() > 1e-2                     # every object its own latent

    def dist(a, b):
        return float(np.linalg.norm(z[a] - z[b]))

    assert dist("box_00", "box_01") < dist("box_00", "mug_00")
    assert dist("cube_050", "cube_060") < dist("cube_050", "capsule_04")
    assert dist("mug_00", "mug_01") < dist("mug_00", "hammer_00")
    cats = [get_object(n).category for n in OBJECT_NAMES]
    same = np.array([[a == b for b in cats] for a in cats]) & ~np.eye(len(cats), dtype=bool)
    assert d[same].mean() < 0.7 * d[~same & ~np.eye(len(cats), dtype=bool)].mean()
    # held-out objects: the nearest training object is one of the same category (holds for these three
    # of the five; hammer_03 lands next to an L-tool and wineglass_03 next to a cone)
    train = training_objects()
    for name in ("box_04", "mug_03", "torus_02"):
        nearest = min(train, key=lambda t: dist(name, t))
        assert get_object(nearest).category == get_object(name).category, (name, nearest)


def test_shipped_reconstructs_far_better_than_untrained(shipped):
    model, meta = shipped
    objs = training_objects()[::5]
    trained = summarize_evaluation(evaluate_encoder(model, objs))["train"]["chamfer_cm2"]
    with torch.random.fork_rng():
        torch.manual_seed(meta["seed"])
        untrained = summarize_evaluation(evaluate_encoder(PointCloudAutoencoder(model.config), objs))
    assert trained < 0.1 * untrained["train"]["chamfer_cm2"]


# ---------------------------------------------------------------------------------- latent hook


def test_encoder_latent_hook():
    from adadex.envs.tracking import TrackingEnv

    z = encoder_latent("mug_00")
    assert z.shape == (64,) and z.dtype == np.float32 and not z.flags.writeable and (np.abs(z) < 1).all()
    assert encoder_latent("mug_00") is z
    with pytest.raises(ValueError):
        z[0] = 0.0
    assert inspect.signature(TrackingEnv.__init__).parameters["latent_fn"].default is encoder_latent
    with pytest.raises(KeyError, match="nope"):
        encoder_latent("nope")


def test_shipped_latent_table_is_the_shipped_encoders_output(shipped):
    """assets/encoder/latents.npz was written from assets/encoder/encoder.pt: recomputing it agrees."""
    table = EncoderLatents(SHIPPED_LATENTS).table
    again = object_latents(shipped[0])
    assert sorted(table) == sorted(OBJECT_NAMES)
    assert max(float(np.abs(table[n] - again[n]).max()) for n in OBJECT_NAMES) < 1e-5


def test_encoder_latents_from_another_run(quick_run, tmp_path):
    path = save_latents(tmp_path / "latents.npz", object_latents(quick_run[0], ["torus_02", "cube_050"]))
    fn = EncoderLatents(path)
    assert fn("torus_02").shape == (64,) and not np.array_equal(fn("torus_02"), encoder_latent("torus_02"))
    with pytest.raises(KeyError, match="mug_00"):
        fn("mug_00")
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        EncoderLatents(tmp_path / "missing.npz")("cube_050")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="junk.npz"):
        EncoderLatents(tmp_path / "junk.npz")("cube_050")


# ---------------------------------------------------------------------------------- CLI


def test_cli_train_and_eval(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["encoder", "train", "--steps", "5", "--out", str(out), "--quiet"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["encoder.json", "encoder.pt", "latents.npz", "reconstructions.png"]
    metrics = json.loads((out / "encoder.json").read_text())
    assert metrics["steps"] == 5 and set(metrics["metrics"]["per_object"]) == set(OBJECT_NAMES)
    assert "Chamfer train" in capsys.readouterr().out
    ev = tmp_path / "ev"
    assert main(["encoder", "eval", str(out / "encoder.pt"), "--out", str(ev)]) == 0
    assert sorted(p.name for p in ev.iterdir()) == ["eval.json", "reconstructions.png"]
    assert "Chamfer" in capsys.readouterr().out


def test_cli_bad_arguments_fail_clearly(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["encoder", "train", "--steps", "-3", "--out", str(out)]) == 2
    assert "steps must be ≥ 0" in capsys.readouterr().err and not out.exists()
    assert main(["encoder", "eval", str(tmp_path / "missing.pt"), "--out", str(out)]) == 2
    assert "missing.pt" in capsys.readouterr().err and not out.exists()
    with pytest.raises(SystemExit) as e:
        main(["encoder", "train", "--steps", "many"])
    assert e.value.code == 2


def test_hydra_recipe(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "recipes" / "train_encoder.py"
    out = tmp_path / "hydra_run"
    r = subprocess.run([sys.executable, str(script), "steps=2", "batch_size=4", f"out={out}", "threads=1"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert {"encoder.pt", "latents.npz", "encoder.json", "reconstructions.png", ".hydra"} <= {p.name for p in out.iterdir()}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hydra_run"]          # nothing else littered
    assert json.loads((out / "encoder.json").read_text())["batch_size"] == 4
