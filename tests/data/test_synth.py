"""Tests of instruction-driven motion synthesis: determinism, plausibility of every verb, paraphrases,
the noise model, and the ray–triangle helper."""

from dataclasses import asdict, fields, replace
from functools import lru_cache

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from adadex.data.human_hand import KEYPOINT_NAMES, NUM_ANGLES, TIP_INDEX
from adadex.data.synth import (
    TEMPLATES,
    VERBS,
    HumanMotion,
    Instruction,
    NoiseConfig,
    Synthesizer,
    make_instruction,
    rest_height,
)
from adadex.geometry import Rotation, first_hits, rotation
from adadex.sim.objects import UnknownObjectError, get_object
from adadex.sim.scene import CONTROL_HZ

OBJECTS = ("cube_050", "mug_00", "bottle_00", "sphere_00")
GRASP_TIPS = [TIP_INDEX[f] for f in ("thumb", "index", "middle", "ring")]   # the little finger has no target
ARRAYS = ("keypoints", "object_pose", "wrist_pose", "angles")


@lru_cache(maxsize=None)
def motion(verb: str, obj: str, clean: bool = True, seed: int = 1) -> HumanMotion:
    synth = Synthesizer(NoiseConfig.clean() if clean else NoiseConfig())
    return synth.synthesize(make_instruction(verb, obj, seed=seed), seed=seed + 1)


@lru_cache(maxsize=None)
def surface(obj: str) -> np.ndarray:
    return get_object(obj).point_cloud(2048).astype(np.float64)


def tip_distances(m: HumanMotion, frames) -> np.ndarray:
    """(len(frames), 4) distance of the grasping fingertips to the object's surface (point cloud)."""
    pc = surface(m.instruction.object_name)
    out = []
    for t in frames:
        pose = m.object_pose[t]
        tree = cKDTree(rotation(pose[3:]).apply(pc) + pose[:3])
        out.append(tree.query(m.keypoints[t, GRASP_TIPS])[0])
    return np.array(out)


# ------------------------------------------------------------------------------------------------
# Determinism


def test_make_instruction_deterministic():
    for verb in VERBS:
        a, b = make_instruction(verb, "mug_00", seed=5), make_instruction(verb, "mug_00", seed=5)
        assert a == b
        assert make_instruction(verb, "mug_00", seed=6).params != a.params, verb


def test_synthesize_deterministic():
    instr = make_instruction("pour", "bottle_00", seed=3)
    a = Synthesizer().synthesize(instr, seed=7)
    b = Synthesizer().synthesize(instr, seed=7)
    for name in ARRAYS:
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.phases == b.phases and a.meta == b.meta
    c = Synthesizer().synthesize(instr, seed=8)
    for name in ARRAYS:
        assert not np.array_equal(getattr(a, name), getattr(c, name)), name


def test_paraphrases_deterministic():
    base = make_instruction("move", "cube_050", seed=2)
    a = Synthesizer().paraphrases(base, 6, seed=4)
    assert a == Synthesizer().paraphrases(base, 6, seed=4)
    b = Synthesizer().paraphrases(base, 6, seed=5)
    assert [p.text for p in a] == [p.text for p in b]       # texts follow the templates …
    assert all(p.style != q.style for p, q in zip(a[1:], b[1:]))   # … motion choices follow the seed


# ------------------------------------------------------------------------------------------------
# Every verb on a few objects (clean motion, so the checks are about the synthesizer, not the noise)


@pytest.mark.parametrize("obj", OBJECTS)
@pytest.mark.parametrize("verb", VERBS)
def test_every_verb_synthesizes(verb, obj):
    m = motion(verb, obj)
    info = get_object(obj)
    T = len(m.keypoints)
    assert m.keypoints.shape == (T, len(KEYPOINT_NAMES), 3)
    assert m.object_pose.shape == m.wrist_pose.shape == (T, 7)
    assert m.angles.shape == (T, NUM_ANGLES)
    assert T >= 312 and m.fps == CONTROL_HZ
    for name in ARRAYS:
        assert np.isfinite(getattr(m, name)).all(), name
    for name in ("object_pose", "wrist_pose"):
        np.testing.assert_allclose(np.linalg.norm(getattr(m, name)[:, 3:], axis=-1), 1.0, atol=1e-9, err_msg=name)
    ph = m.phases
    assert 0 < ph["approach"] < ph["grasp"] < ph["manipulate"] < ph["release"] < ph["retreat"] < T, ph
    assert m.meta["verb"] == verb and m.meta["phases"] == ph

    # The hand starts far from the object, which rests on the table.
    palm = 0.5 * (m.keypoints[:, 0] + m.keypoints[:, 4])     # wrist and middle knuckle
    assert np.linalg.norm(m.keypoints[0, 0] - m.object_pose[0, :3]) > 0.20
    assert np.linalg.norm(palm[0] - m.object_pose[0, :3]) > 0.20
    assert m.object_pose[0, 2] == pytest.approx(info.half_height + 1e-3, abs=1e-9)
    # The object does not move before the grasp, and ends at rest on the table.
    assert np.array_equal(m.object_pose[: ph["manipulate"]], np.broadcast_to(m.object_pose[0], (ph["manipulate"], 7)))
    if verb != "push":
        end = m.object_pose[-1]
        assert end[2] == pytest.approx(rest_height(obj, rotation(end[3:])), abs=1e-6)

    # Grasp: the grasping fingertips are on the object's surface from the closed grasp until release
    # (the fingertip keypoint is the pad's centre, ~1 cm out; a finger beside a small object ~2 cm).
    d = tip_distances(m, range(ph["manipulate"], ph["release"]))
    t, k = np.unravel_index(int(d.argmax()), d.shape)
    assert d.max() < 0.03, f"fingertip {k} is {d.max() * 100:.1f} cm from the object at frame {ph['manipulate'] + t}"
    # … and the hand is not at the object before it gets there.
    assert tip_distances(m, [0]).min() > 0.05


@pytest.mark.parametrize("verb", VERBS)
def test_object_stays_above_table(verb):
    """No pose of the object's trajectory puts it through the table (beyond its 1 mm rest clearance)."""
    for obj in OBJECTS:
        m = motion(verb, obj)
        pc = surface(obj)
        low = [float((rotation(p[3:]).apply(pc)[:, 2] + p[2]).min()) for p in m.object_pose[::3]]
        assert min(low) > -2e-3, f"{obj}: {min(low) * 1000:.1f} mm below the table"


def test_hand_starts_far_from_objects_near_the_robot():
    """Regression: the start is pushed out to 0.3 m from the robot's base axis, which for an object near
    the robot moved the hand toward it (palm as near as 0.19 m, too near for an episode to start)."""
    for y0 in (-0.12, 0.0, 0.12):
        for yaw in (-0.9, 0.0, 0.9):
            base = make_instruction("shake", "mug_03", seed=0)
            instr = replace(base, params=dict(base.params, x0=-0.06, y0=y0), style=dict(base.style, approach_yaw=yaw))
            for seed in range(3):
                m = Synthesizer().synthesize(instr, seed=seed)
                palm = 0.5 * (m.keypoints[0, 0] + m.keypoints[0, 4])
                assert np.linalg.norm(m.keypoints[0, 0] - m.object_pose[0, :3]) > 0.28, (y0, yaw, seed)
                assert np.linalg.norm(palm - m.object_pose[0, :3]) > 0.22, (y0, yaw, seed)
                assert np.linalg.norm(m.wrist_pose[0, :2]) >= 0.3 - 0.03     # still clear of the base axis


def test_noisy_motion_is_plausible():
    """With the default noise the hand still starts far away and the tips are near the object at the grasp."""
    for verb in ("lift", "pour", "shake"):
        for obj in ("cube_050", "mug_00"):
            m = motion(verb, obj, clean=False)
            for name in ARRAYS:
                assert np.isfinite(getattr(m, name)).all()
            assert np.linalg.norm(m.keypoints[0, 0] - m.object_pose[0, :3]) > 0.20
            assert m.object_pose[0, 2] == pytest.approx(get_object(obj).half_height + 1e-3, abs=0.01)
            assert np.median(tip_distances(m, [m.phases["manipulate"]])) < 0.03, (verb, obj)


def test_unknown_verb_or_object():
    with pytest.raises(ValueError, match="unknown verb 'juggle'"):
        make_instruction("juggle", "mug_00", seed=0)
    with pytest.raises(UnknownObjectError):
        make_instruction("lift", "mgu_00", seed=0)


# ------------------------------------------------------------------------------------------------
# Paraphrases


def test_paraphrases():
    for verb in VERBS:
        base = make_instruction(verb, "mug_00", seed=11)
        n = len(TEMPLATES[verb])
        out = Synthesizer().paraphrases(base, n, seed=12)
        assert len(out) == n and out[0] is base
        texts = [p.text for p in out]
        assert len(set(texts)) == n, texts
        for k, p in enumerate(out):
            assert isinstance(p, Instruction)
            assert (p.verb, p.object_name, p.params, p.paraphrase) == (verb, "mug_00", base.params, k)
            assert "{" not in p.text and "mug" in p.text
        styles = [p.style for p in out]
        assert all(styles[i] != styles[j] for i in range(n) for j in range(i)), styles
        assert set(styles[1]) == set(base.style)


def test_paraphrase_count_limits():
    base = make_instruction("lift", "cube_050", seed=0)
    assert len(Synthesizer().paraphrases(base, 10, seed=0)) == 10
    assert Synthesizer().paraphrases(base, 1, seed=0) == [base]
    for n in (0, 11, -1):
        with pytest.raises(ValueError, match=r"paraphrases per instruction must be in 1\.\.10, got " + str(n)):
            Synthesizer().paraphrases(base, n, seed=0)


def test_ten_paraphrases_all_differ_from_the_base_text():
    for verb in VERBS:
        base = make_instruction(verb, "mug_00", seed=11)
        out = Synthesizer().paraphrases(base, 10, seed=12)
        assert len({p.text for p in out}) == 10, verb


def test_templates_cover_the_verbs():
    assert len(VERBS) >= 8 and set(TEMPLATES) == set(VERBS)
    for verb in VERBS:
        assert len(TEMPLATES[verb]) >= 4, verb
        assert len(set(TEMPLATES[verb])) == len(TEMPLATES[verb]), verb


def test_instruction_text_carries_the_parameters():
    lift = make_instruction("lift", "cube_050", seed=0)
    assert lift.text == f"lift the cube {round(100 * lift.params['h'])} cm"
    rot = make_instruction("rotate", "mug_00", seed=0)
    assert f"{round(abs(np.degrees(rot.params['angle'])))} degrees" in rot.text
    place = make_instruction("place", "bottle_00", seed=0)
    assert place.params["side"] in place.text and np.sign(place.params["dy"]) == (1 if place.params["side"] == "left" else -1)


# ------------------------------------------------------------------------------------------------
# Noise


def still_second_differences(m: HumanMotion) -> np.ndarray:
    """Second differences of the keypoints over the still phase (hand at rest before the approach)."""
    kp = m.keypoints[: m.phases["approach"]]
    assert len(kp) >= 6
    return np.diff(kp, n=2, axis=0)


def test_clean_motion_has_no_jitter():
    m = motion("lift", "cube_050", clean=True)
    assert np.abs(still_second_differences(m)).max() < 1e-12
    # The object does not move at all before the grasp, and the whole motion is smooth.
    assert np.ptp(m.object_pose[: m.phases["manipulate"]], axis=0).max() == 0.0
    assert np.abs(np.diff(m.keypoints, n=2, axis=0)).max() < 0.01


@pytest.mark.parametrize("jitter, jitter_rot", [(0.002, 0.01), (0.006, 0.03)])
def test_jitter_has_the_configured_size(jitter, jitter_rot):
    noise = NoiseConfig(jitter=jitter, jitter_rot=jitter_rot)
    m = Synthesizer(noise).synthesize(make_instruction("lift", "mug_00", seed=1), seed=2)
    # Independent N(0, σ²) per frame: second differences have variance 6σ².
    est = still_second_differences(m).std() / np.sqrt(6)
    assert est == pytest.approx(jitter, rel=0.2)
    # The object rests until the grasp: its position and orientation scatter around the rest pose.
    still = m.object_pose[: m.phases["manipulate"]]
    rest = np.array([*still[:, :3].mean(0)])
    assert np.std(still[:, :3] - rest) == pytest.approx(jitter, rel=0.25)
    yaw0 = Rotation.from_euler("z", m.instruction.params["yaw0"])
    rotvec = (rotation(still[:, 3:]) * yaw0.inv()).as_rotvec()
    assert np.sqrt((rotvec ** 2).mean()) == pytest.approx(jitter_rot, rel=0.25)


@pytest.mark.parametrize("name", [f.name for f in fields(NoiseConfig)])
@pytest.mark.parametrize("value", [-0.001, float("nan"), float("inf")])
def test_invalid_noise_config(name, value):
    with pytest.raises(ValueError, match=f"NoiseConfig.{name} must be a finite number ≥ 0"):
        NoiseConfig(**{name: value})


def test_clean_noise_config_is_all_zero():
    assert all(v == 0.0 for v in asdict(NoiseConfig.clean()).values())


# ------------------------------------------------------------------------------------------------
# Ray casting


def box_hits(extents, origins, dirs):
    """Analytic first hit distance of rays with an axis-aligned box centred at the origin (slab method)."""
    half = np.asarray(extents) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - origins) / dirs
        t2 = (half - origins) / dirs
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (near <= far) & (far > 0)
    return np.where(hit, np.where(near > 0, near, far), np.inf)


def test_first_hits_matches_analytic_box():
    extents = (0.1, 0.2, 0.3)
    box = trimesh.creation.box(extents=extents)
    rng = np.random.default_rng(0)
    n = 300
    origins = rng.uniform(-0.4, 0.4, (n, 3))
    origins[:20] = rng.uniform(-0.04, 0.04, (20, 3))           # some start inside the box
    targets = rng.uniform(-0.08, 0.08, (n, 3))
    dirs = targets - origins
    dirs[::3] = rng.normal(size=(len(dirs[::3]), 3))           # and some point anywhere (many miss)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dist, tri = first_hits(box.triangles, origins, dirs)
    want = box_hits(extents, origins, dirs)
    assert np.isfinite(want).sum() > 150 and np.isinf(want).sum() > 20
    np.testing.assert_allclose(dist, want, atol=1e-9)
    np.testing.assert_array_equal(tri == -1, np.isinf(want))
    # The reported triangle contains the hit point.
    hit = np.isfinite(dist)
    p = origins[hit] + dist[hit, None] * dirs[hit]
    normals, v0 = box.face_normals[tri[hit]], box.triangles[tri[hit], 0]
    np.testing.assert_allclose(np.einsum("ij,ij->i", p - v0, normals), 0.0, atol=1e-9)


def test_first_hits_axis_aligned_rays():
    """Rays parallel to some faces (zero determinant for those triangles) still hit the facing one."""
    box = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    origins = np.array([[-1.0, 0.01, 0.02], [0.0, 1.0, 0.0], [0.03, -0.02, -2.0], [0.0, 0.0, 0.0], [0.2, 0.2, 0.0]])
    dirs = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, 1.0], [1.0, 0, 0]])
    dist, tri = first_hits(box.triangles, origins, dirs)
    np.testing.assert_allclose(dist[:4], [0.95, 0.9, 1.85, 0.15], atol=1e-12)
    assert dist[4] == np.inf and tri[4] == -1
    np.testing.assert_allclose(box.face_normals[tri[:4]], [[-1, 0, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], atol=1e-12)
