import mujoco
import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull, Delaunay

from adadex.sim import objects
from adadex.sim.objects import (
    CATEGORIES,
    OBJECT_NAMES,
    REGISTRY,
    UnknownObjectError,
    add_object_geoms,
    get_object,
    held_out_objects,
    object_split,
)

ALL = pytest.mark.parametrize("name", OBJECT_NAMES)
REQUIRED_CATEGORIES = {"box", "cylinder", "bottle", "sphere", "mug", "hammer", "stamp", "torus", "cone",
                       "plate", "l_tool", "wineglass"}


def _distance_to_surface(mesh: trimesh.Trimesh, points: np.ndarray, tol: float) -> np.ndarray:
    """Upper bound on each point's distance to ``mesh``, exact when it is below ``tol``.

    Brute force without rtree: only triangles whose box, grown by ``tol``, holds the point.
    """
    tri = mesh.triangles
    lo, hi = tri.min(axis=1) - tol, tri.max(axis=1) + tol
    out = np.full(len(points), np.inf)
    for k, p in enumerate(points.astype(np.float64)):
        cand = np.flatnonzero(np.all((p >= lo) & (p <= hi), axis=1))
        if len(cand):
            closest = trimesh.triangles.closest_point(tri[cand], np.repeat(p[None], len(cand), axis=0))
            out[k] = np.linalg.norm(closest - p, axis=1).min()
    return out


def _compile_single(name: str) -> mujoco.MjModel:
    spec = mujoco.MjSpec()
    body = spec.worldbody.add_body(name="obj", pos=[0, 0, get_object(name).half_height])
    body.add_freejoint()
    add_object_geoms(spec, body, name)
    return spec.compile()


def test_registry_size_categories_and_split():
    assert len(REGISTRY) >= 50
    assert OBJECT_NAMES == tuple(REGISTRY)
    assert len(CATEGORIES) >= 10
    assert REQUIRED_CATEGORIES <= set(CATEGORIES)
    assert set(CATEGORIES) == {o.category for o in REGISTRY.values()}
    for c in CATEGORIES:
        assert sum(o.category == c for o in REGISTRY.values()) >= 4, c
    for name, info in REGISTRY.items():
        assert info.name == name and name.startswith(info.category + "_")
    held = held_out_objects()
    assert len(held) == 5
    assert len({REGISTRY[n].category for n in held}) >= 4
    assert [object_split(n) for n in held] == ["held_out"] * 5
    assert sum(object_split(n) == "train" for n in OBJECT_NAMES) == len(OBJECT_NAMES) - 5
    # Every category keeps training objects; names used elsewhere in adadex exist.
    for c in CATEGORIES:
        assert any(o.category == c and not o.held_out for o in REGISTRY.values())
    assert object_split("box_00") == object_split("cube_050") == "train"
    assert get_object("cube_050").mesh().extents == pytest.approx([0.05] * 3)


@ALL
def test_geometry_is_sound(name):
    info = get_object(name)
    parts = info.parts()
    assert parts
    for p in parts:
        assert p.is_watertight and p.is_convex and p.volume > 0
    mesh = info.mesh()
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert len(mesh.split(only_watertight=False)) == 1
    # Parts barely overlap, so MuJoCo (which sums part volumes) gets the right mass.
    assert sum(p.volume for p in parts) == pytest.approx(mesh.volume, rel=0.02)
    part_bounds = np.array([p.bounds for p in parts])
    np.testing.assert_allclose(mesh.bounds, [part_bounds[:, 0].min(axis=0), part_bounds[:, 1].max(axis=0)],
                               atol=1e-6)


@ALL
def test_size_mass_and_frame(name):
    info = get_object(name)
    mesh = info.mesh()
    ext = mesh.extents
    assert 0.03 <= ext.max() <= 0.25
    assert ext.min() >= 0.01
    assert 0.02 <= info.mass <= 1.0
    assert info.mass == pytest.approx(info.density * mesh.volume)
    assert 300 <= info.density <= 1200
    np.testing.assert_allclose(mesh.bounds.sum(axis=0), 0.0, atol=1e-6)
    assert info.half_height == -mesh.bounds[0, 2]
    assert info.half_height == pytest.approx(ext[2] / 2, abs=1e-6)


@pytest.mark.parametrize("name", [n for n in OBJECT_NAMES if get_object(n).category not in ("sphere", "capsule")])
def test_rests_stably_in_canonical_pose(name):
    """The centre of mass lies over the support polygon (spheres and capsules roll; skipped)."""
    mesh = get_object(name).mesh()
    low = mesh.vertices[mesh.vertices[:, 2] < mesh.bounds[0, 2] + 1e-6, :2]
    hull = low[ConvexHull(low).vertices]
    com = mesh.center_mass[:2]
    assert Delaunay(hull).find_simplex(com) >= 0


def test_point_cloud_deterministic_and_on_surface():
    for name in OBJECT_NAMES:
        info = get_object(name)
        a = info.point_cloud(256, seed=3)
        assert a.shape == (256, 3) and a.dtype == np.float32
        np.testing.assert_array_equal(a, info.point_cloud(256, seed=3))
        assert not np.allclose(a, info.point_cloud(256, seed=4))
        assert _distance_to_surface(info.mesh(), a, 1e-4).max() < 1e-4, name
    assert get_object("mug_00").point_cloud().shape == (1024, 3)


def test_returned_meshes_are_copies():
    info = get_object("mug_00")
    m = info.mesh()
    m.apply_translation([1.0, 0, 0])
    info.parts()[0].apply_translation([1.0, 0, 0])
    assert info.mesh().bounds[0, 0] < 0 and info.parts()[0].bounds[0, 0] < 0
    assert info.half_height == -info.mesh().bounds[0, 2]


@ALL
def test_mujoco_geoms_and_mass(name):
    info = get_object(name)
    model = _compile_single(name)
    body = model.body("obj")
    assert body.mass[0] == pytest.approx(info.mass, rel=0.02)
    geoms = [model.geom(i) for i in range(model.ngeom) if model.geom_bodyid[i] == body.id]
    assert len(geoms) == len(info.parts()) == model.nmesh
    for g in geoms:
        assert g.type[0] == mujoco.mjtGeom.mjGEOM_MESH
        assert g.condim[0] == 4 and g.contype[0] == 1 and g.conaffinity[0] == 1
        np.testing.assert_allclose(g.friction, [1.0, 0.01, 0.001])
    # Inertia comes from the mesh: the principal moments match trimesh's for the union.
    np.testing.assert_allclose(np.sort(body.inertia), np.sort(np.linalg.eigvalsh(info.mesh().moment_inertia
                                                                                 * info.density)),
                               rtol=0.05)


def test_object_pose_matches_geometry_after_compile():
    """MuJoCo re-centres meshes on their centroids; the geoms must still be where the parts are."""
    model = _compile_single("hammer_01")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    info = get_object("hammer_01")
    np.testing.assert_allclose(data.subtree_com[model.body("obj").id] - [0, 0, info.half_height],
                               info.mesh().center_mass, atol=2e-4)


def test_two_objects_in_one_spec_and_options():
    spec = mujoco.MjSpec()
    b1 = spec.worldbody.add_body(name="a", pos=[0, 0, 0.1])
    b1.add_freejoint()
    b2 = spec.worldbody.add_body(name="b", pos=[0.3, 0, 0.1])
    b2.add_freejoint()
    b3 = spec.worldbody.add_body(name="c", pos=[-0.3, 0, 0.1])
    b3.add_freejoint()
    add_object_geoms(spec, b1, "mug_00", friction=(0.7, 0.02, 0.002), rgba=(1, 0, 0, 1))
    add_object_geoms(spec, b2, "torus_00")
    add_object_geoms(spec, b3, "mug_00")
    model = spec.compile()
    n_mug, n_torus = len(get_object("mug_00").parts()), len(get_object("torus_00").parts())
    assert model.nmesh == n_mug + n_torus
    assert model.body("a").mass[0] == pytest.approx(model.body("c").mass[0])
    g = model.geom("a_mug_00_part0")
    np.testing.assert_allclose(g.friction, [0.7, 0.02, 0.002])
    np.testing.assert_allclose(g.rgba, [1, 0, 0, 1])
    assert model.geom("b_torus_00_part0").rgba[3] == 1.0


def test_unknown_name_suggests_close_matches():
    with pytest.raises(UnknownObjectError) as e:
        get_object("mug_3")
    msg = str(e.value)
    assert "mug_03" in msg and str(len(OBJECT_NAMES)) in msg
    assert isinstance(e.value, KeyError)
    with pytest.raises(UnknownObjectError, match="cube_050"):
        object_split("cube_50")
    spec = mujoco.MjSpec()
    with pytest.raises(UnknownObjectError):
        add_object_geoms(spec, spec.worldbody, "no_such_thing")


def test_build_is_cached():
    assert objects._mesh(get_object("mug_00")) is objects._mesh(get_object("mug_00"))


@pytest.mark.parametrize("scale", [0.8, 1.0, 1.2])
def test_resting_height_is_read_from_the_compiled_scene(scale):
    """The tracking env puts a resized object on the table from the compiled scene alone (collector
    workers get compiled scenes and build no mesh): the height it reads is the object's scaled
    half height."""
    from adadex.sim.scene import build_scene_model, resting_height

    model = build_scene_model("mug_04", object_scale=scale)
    assert resting_height(model) == pytest.approx(scale * get_object("mug_04").half_height, abs=1e-12)
