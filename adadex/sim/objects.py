"""Procedural object library: graspable everyday shapes built in code from convex pieces.

Every object is a small compound of convex, watertight trimesh primitives (boxes, cylinders,
hulls of circles, ...), so MuJoCo can collide each piece as the convex mesh it is and compute
mass and inertia from it, while :meth:`ObjectInfo.mesh` gives the exact union for point clouds
and rendering. No mesh files are shipped: the parameters of every object are written below, so
the library is deterministic and reviewable.

The objects are sized for a LEAP-like hand (fingers about 10 cm long): the largest extent of
every object lies between 3 and 25 cm, the smallest is at least 1 cm and masses lie between
20 g and 1 kg. Five objects, in five different categories, form the held-out (unseen-object)
split; every category keeps training objects.

Object frame: z up in the canonical resting pose, origin at the centre of the bounding box, so an
object rests on a table when its origin is :attr:`ObjectInfo.half_height` above it. Units are SI.

Names are ``<category>_<NN>``, except cubes, which are ``cube_<side in mm>`` (``cube_050`` is the
5 cm cube used by the scripted grasp).

Example
-------
>>> import mujoco
>>> from adadex.sim import objects
>>> info = objects.get_object("mug_00")
>>> info.category, objects.object_split("mug_00")
('mug', 'train')
>>> info.point_cloud(256).shape
(256, 3)
>>> spec = mujoco.MjSpec()
>>> body = spec.worldbody.add_body(name="object", pos=[0, 0, info.half_height])
>>> _ = body.add_freejoint()
>>> objects.add_object_geoms(spec, body, "mug_00")
>>> model = spec.compile()
>>> round(float(model.body("object").mass[0]), 3), round(info.mass, 3)
(0.166, 0.165)
"""

from __future__ import annotations

import difflib
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from adadex.errors import AdadexError, ConfigError

if TYPE_CHECKING:
    import trimesh

_SECTIONS = 32
_TUBE_SECTIONS = 16
_OVERLAP = 5e-5


def _trimesh():
    """trimesh, imported when a mesh is first built: collector workers step scenes compiled elsewhere and
    never need it, and importing it was 0.8 s of each worker's start."""
    import trimesh

    return trimesh


# --------------------------------------------------------------------------------------------
# Convex primitives


def _hull(points) -> trimesh.Trimesh:
    return _trimesh().convex.convex_hull(np.asarray(points, dtype=np.float64))


def _ring(radius: float, z: float, sections: int = _SECTIONS, phase: float = 0.0) -> np.ndarray:
    a = phase + np.linspace(0.0, 2.0 * np.pi, sections, endpoint=False)
    return np.column_stack([radius * np.cos(a), radius * np.sin(a), np.full(sections, z)])


def _lathe(profile: Sequence[tuple[float, float]], sections: int = _SECTIONS,
           phase: float = 0.0) -> trimesh.Trimesh:
    """Convex hull of horizontal circles ``(z, r)``; ``r == 0`` is a single point (an apex)."""
    pts = [np.array([[0.0, 0.0, z]]) if r == 0 else _ring(r, z, sections, phase) for z, r in profile]
    return _hull(np.vstack(pts))


def _cylinder(radius: float, z0: float, z1: float, sections: int = _SECTIONS) -> trimesh.Trimesh:
    return _lathe([(z0, radius), (z1, radius)], sections)


def _box(extents, center=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    b = _trimesh().creation.box(extents=extents)
    b.apply_translation(center)
    return b


def _box_between(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return _box(hi - lo, (lo + hi) / 2.0)


def _rotated(mesh: trimesh.Trimesh, angle: float, axis) -> trimesh.Trimesh:
    mesh.apply_transform(_trimesh().transformations.rotation_matrix(angle, axis))
    return mesh


def _tube(centers: np.ndarray, tangents: np.ndarray, plane_normal, radius: float,
          sections: int = _TUBE_SECTIONS) -> list[trimesh.Trimesh]:
    """A bent rod along a planar path, as hulls of consecutive cross-section circles.

    Each piece reaches :data:`_OVERLAP` past the shared cross-sections, so neighbours overlap
    by a sliver instead of sharing a tilted face, which the boolean union (float32) cannot
    resolve cleanly.
    """
    n = np.asarray(plane_normal, float)
    a = np.linspace(0.0, 2.0 * np.pi, sections, endpoint=False)
    tangents = tangents / np.linalg.norm(tangents, axis=1, keepdims=True)
    offsets = [radius * (np.outer(np.cos(a), n) + np.outer(np.sin(a), np.cross(t, n))) for t in tangents]
    return [_hull(np.vstack([centers[i] - _OVERLAP * tangents[i] + offsets[i],
                             centers[i + 1] + _OVERLAP * tangents[i + 1] + offsets[i + 1]]))
            for i in range(len(centers) - 1)]


# --------------------------------------------------------------------------------------------
# Category builders: each returns the convex parts of one object in its resting pose (z up); the
# registry recentres them on the bounding box.


def _box_parts(extents) -> list[trimesh.Trimesh]:
    """A rectangular block, resting on its x-y face."""
    return [_box(extents)]


def _cylinder_parts(radius: float, height: float) -> list[trimesh.Trimesh]:
    """An upright solid cylinder."""
    return [_cylinder(radius, 0.0, height)]


def _bottle_parts(radius: float, body_h: float, shoulder_h: float, neck_r: float, neck_h: float,
                  cap_r: float, cap_h: float, square: bool = False) -> list[trimesh.Trimesh]:
    """Upright bottle: body, shoulder tapering to the neck, neck and a cap (round or square body)."""
    z1, z2, z3 = body_h, body_h + shoulder_h, body_h + shoulder_h + neck_h
    if square:
        body = _box_between((-radius, -radius, 0.0), (radius, radius, z1))
        top = np.array([[sx * radius, sy * radius, z1] for sx in (-1, 1) for sy in (-1, 1)])
        shoulder = _hull(np.vstack([top, _ring(neck_r, z2)]))
    else:
        body = _cylinder(radius, 0.0, z1)
        shoulder = _lathe([(z1, radius), (z2, neck_r)])
    return [body, shoulder, _cylinder(neck_r, z2, z3), _cylinder(cap_r, z3, z3 + cap_h)]


def _sphere_parts(radii) -> list[trimesh.Trimesh]:
    """A ball, or an ellipsoid with semi-axes ``radii`` resting on its shortest axis."""
    s = _trimesh().creation.icosphere(subdivisions=3, radius=1.0)
    s.apply_scale(np.broadcast_to(np.asarray(radii, float), (3,)))
    return [s]


def _mug_parts(radius: float, height: float, wall: float, bottom: float, handle_reach: float,
               handle_half_height: float, handle_r: float, segments: int = 12,
               arc_points: int = 3) -> list[trimesh.Trimesh]:
    """Open mug: a floor disc, a wall of ``segments`` convex sectors and a bent-rod handle on +x.

    Each wall sector is the hull of its outer arc and inner chord, widened by :data:`_OVERLAP`
    at both ends so neighbours overlap slightly; the floor meets the wall on ``z = bottom``.
    """
    outer_n = segments * arc_points
    parts = [_cylinder(radius, 0.0, bottom, outer_n)]
    r_in = radius - wall
    for i in range(segments):
        ang_out = 2 * np.pi * (i * arc_points + np.arange(arc_points + 1)) / outer_n
        ang_out[[0, -1]] += np.array([-1.0, 1.0]) * _OVERLAP / r_in
        ang_in = ang_out[[0, -1]]
        ring = np.vstack([np.column_stack([radius * np.cos(ang_out), radius * np.sin(ang_out)]),
                          np.column_stack([r_in * np.cos(ang_in), r_in * np.sin(ang_in)])])
        pts = np.vstack([np.column_stack([ring, np.full(len(ring), z)]) for z in (bottom, height)])
        parts.append(_hull(pts))
    embed = 0.5 * wall
    cx, cz = radius - embed, (bottom + height) / 2.0
    phi = np.linspace(-np.pi / 2, np.pi / 2, 9)
    ax = handle_reach + embed
    centers = np.column_stack([cx + ax * np.cos(phi), np.zeros_like(phi), cz + handle_half_height * np.sin(phi)])
    tangents = np.column_stack([-ax * np.sin(phi), np.zeros_like(phi), handle_half_height * np.cos(phi)])
    parts += _tube(centers, tangents, (0.0, 1.0, 0.0), handle_r)
    return parts


def _hammer_parts(handle_len: float, thickness: float, head_len: float, head_width: float,
                  claw: float = 0.0, face: bool = False) -> list[trimesh.Trimesh]:
    """Hammer lying flat: a round handle along +x and a head along y, both ``thickness`` thick.

    ``claw`` > 0 adds a tapering claw of that length on the -y end; ``face`` adds a round striking
    face on the +y end.
    """
    t, hw = thickness, head_width
    handle = _rotated(_cylinder(t / 2, hw / 2, hw / 2 + handle_len), np.pi / 2, (0, 1, 0))
    parts = [_box((hw, head_len, t)), handle]
    y0, y1 = -head_len / 2, head_len / 2
    if claw > 0:
        base = np.array([[sx * hw / 2, y0, sz * t / 2] for sx in (-1, 1) for sz in (-1, 1)])
        tip = np.array([[-hw / 2 + sx * 0.3 * hw, y0 - claw, sz * t / 2] for sx in (0, 1) for sz in (-1, 1)])
        parts.append(_hull(np.vstack([base, tip])))
    if face:
        cyl = _rotated(_cylinder(t / 2, 0.0, 0.2 * head_len), -np.pi / 2, (1, 0, 0))
        cyl.apply_translation((0.0, y1, 0.0))
        parts.append(cyl)
    return parts


def _stamp_parts(block, handle_r: float, handle_h: float, knob_r: float,
                 round_block: bool = False) -> list[trimesh.Trimesh]:
    """Upright stamp: a block (box or disc) with a vertical handle and a ball knob on top."""
    bz = block[2]
    base = _cylinder(block[0] / 2, 0.0, bz) if round_block else _box_between(
        (-block[0] / 2, -block[1] / 2, 0.0), (block[0] / 2, block[1] / 2, bz))
    z_top = bz + handle_h
    z_cut = -np.sqrt(knob_r**2 - handle_r**2)
    zs = np.linspace(z_cut, knob_r, 9)
    radii = np.sqrt(np.clip(knob_r**2 - zs**2, 0.0, None))
    knob = _lathe([(z_top - z_cut + z, r) for z, r in zip(zs, radii)], 24)
    return [base, _cylinder(handle_r, bz, z_top), knob]


def _torus_parts(major_r: float, minor_r: float, segments: int = 16) -> list[trimesh.Trimesh]:
    """A ring lying flat, as ``segments`` convex tube pieces."""
    a = np.linspace(0.0, 2 * np.pi, segments + 1)
    centers = np.column_stack([major_r * np.cos(a), major_r * np.sin(a), np.zeros_like(a)])
    tangents = np.column_stack([-np.sin(a), np.cos(a), np.zeros_like(a)])
    return _tube(centers, tangents, (0.0, 0.0, 1.0), minor_r)


def _cone_parts(bottom_r: float, top_r: float, height: float) -> list[trimesh.Trimesh]:
    """A cone (``top_r = 0``) or frustum standing on its bottom face."""
    return [_lathe([(0.0, bottom_r), (height, top_r)])]


def _plate_parts(bottom_r: float, top_r: float, thickness: float) -> list[trimesh.Trimesh]:
    """A flat disc; ``top_r > bottom_r`` bevels the rim like a dinner plate."""
    return [_lathe([(0.0, bottom_r), (thickness, top_r)], 48)]


def _l_tool_parts(long_len: float, long_w: float, short_len: float, short_w: float,
                  thickness: float, round_bar: bool = False) -> list[trimesh.Trimesh]:
    """An L lying flat: a long arm along +x and a short arm along +y meeting at the corner.

    With ``round_bar`` (a hex-key-like tool) the arms are rods of diameter ``thickness`` joined by
    a corner block.
    """
    t = thickness
    if round_bar:
        corner = _box_between((0.0, 0.0, 0.0), (t, t, t))
        arm_x = _rotated(_cylinder(t / 2, 0.0, long_len - t), np.pi / 2, (0, 1, 0))
        arm_x.apply_translation((t, t / 2, t / 2))
        arm_y = _rotated(_cylinder(t / 2, 0.0, short_len - t), -np.pi / 2, (1, 0, 0))
        arm_y.apply_translation((t / 2, t, t / 2))
        return [corner, arm_x, arm_y]
    return [_box_between((0.0, 0.0, 0.0), (long_len, long_w, t)),
            _box_between((0.0, long_w, 0.0), (short_w, short_len, t))]


def _wineglass_parts(base_r: float, base_h: float, stem_r: float, stem_h: float,
                     bowl: Sequence[tuple[float, float]]) -> list[trimesh.Trimesh]:
    """Upright stemmed glass: foot disc, stem and a solid convex bowl given as ``(dz, r)`` rings."""
    z0 = base_h + stem_h
    return [_cylinder(base_r, 0.0, base_h, 40), _cylinder(stem_r, base_h, z0, 16),
            _lathe([(z0 + dz, r) for dz, r in bowl], 40)]


def _spherical_bowl(radius: float, bottom_r: float, rings: int = 7) -> tuple[tuple[float, float], ...]:
    """``(dz, r)`` rings of a hemispherical bowl cut flat at radius ``bottom_r`` (a goblet)."""
    a = np.linspace(np.arcsin(bottom_r / radius), np.pi / 2, rings)
    return tuple(zip(radius * (np.cos(a[0]) - np.cos(a)), radius * np.sin(a)))


def _capsule_parts(radius: float, length: float, sections: int = 16) -> list[trimesh.Trimesh]:
    """A capsule lying along x on one of its flat facets (on an edge it would roll off);
    ``length`` is the distance between the hemisphere centres."""
    c = _trimesh().creation.capsule(height=length, radius=radius, count=[sections, sections])
    _rotated(c, np.pi / 2, (0, 1, 0))
    return [_rotated(c, np.pi / sections, (1, 0, 0))]


def _pyramid_parts(sides: int, base_r: float, height: float, top_r: float = 0.0) -> list[trimesh.Trimesh]:
    """A regular pyramid (or frustum) on its base; ``base_r`` is the base circumradius."""
    return [_lathe([(0.0, base_r), (height, top_r)], sides, phase=np.pi / sides)]


# --------------------------------------------------------------------------------------------
# Registry


@dataclass(frozen=True)
class ObjectInfo:
    """One library object. ``builder`` returns its convex parts in an arbitrary frame."""

    name: str
    category: str
    held_out: bool
    density: float
    builder: Callable[[], list[trimesh.Trimesh]] = field(repr=False)

    def parts(self) -> list[trimesh.Trimesh]:
        """Convex, watertight pieces in the object frame (copies; safe to modify)."""
        return [p.copy() for p in _parts(self)]

    def mesh(self) -> trimesh.Trimesh:
        """Watertight union of :meth:`parts` (a copy; safe to modify)."""
        return _mesh(self).copy()

    @property
    def mass(self) -> float:
        return float(self.density * _mesh(self).volume)

    @property
    def half_height(self) -> float:
        """Height of the origin above the table when the object rests in its canonical pose."""
        return float(-_mesh(self).bounds[0, 2])

    def point_cloud(self, n: int = 1024, seed: int = 0) -> np.ndarray:
        """``(n, 3)`` float32 points sampled uniformly on the surface, deterministic per seed."""
        pts, _ = _trimesh().sample.sample_surface(_mesh(self), n, seed=seed)
        return np.asarray(pts, dtype=np.float32)


@functools.lru_cache(maxsize=None)
def _parts(info: ObjectInfo) -> tuple[trimesh.Trimesh, ...]:
    parts = info.builder()
    verts = np.vstack([p.vertices for p in parts])
    center = (verts.min(axis=0) + verts.max(axis=0)) / 2.0
    for p in parts:
        p.apply_translation(-center)
    return tuple(parts)


@functools.lru_cache(maxsize=None)
def _mesh(info: ObjectInfo) -> trimesh.Trimesh:
    parts = _parts(info)
    if len(parts) == 1:
        return parts[0].copy()
    return _trimesh().boolean.union(list(parts), engine="manifold")


_P = functools.partial

# (name, category, density kg/m^3, builder); parameters in metres.
_TABLE: tuple[tuple[str, str, float, Callable[[], list[trimesh.Trimesh]]], ...] = (
    ("box_00", "box", 500, _P(_box_parts, (0.08, 0.05, 0.04))),
    ("box_01", "box", 450, _P(_box_parts, (0.12, 0.06, 0.03))),
    ("box_02", "box", 500, _P(_box_parts, (0.05, 0.05, 0.10))),
    ("box_03", "box", 600, _P(_box_parts, (0.16, 0.04, 0.04))),
    ("box_04", "box", 500, _P(_box_parts, (0.10, 0.07, 0.02))),
    ("box_05", "box", 700, _P(_box_parts, (0.20, 0.03, 0.02))),

    ("cube_030", "cube", 1000, _P(_box_parts, (0.03, 0.03, 0.03))),
    ("cube_040", "cube", 500, _P(_box_parts, (0.04, 0.04, 0.04))),
    ("cube_050", "cube", 700, _P(_box_parts, (0.05, 0.05, 0.05))),
    ("cube_060", "cube", 300, _P(_box_parts, (0.06, 0.06, 0.06))),
    ("cube_070", "cube", 300, _P(_box_parts, (0.07, 0.07, 0.07))),

    ("cylinder_00", "cylinder", 800, _P(_cylinder_parts, 0.010, 0.12)),
    ("cylinder_01", "cylinder", 700, _P(_cylinder_parts, 0.020, 0.10)),
    ("cylinder_02", "cylinder", 600, _P(_cylinder_parts, 0.030, 0.08)),
    ("cylinder_03", "cylinder", 700, _P(_cylinder_parts, 0.040, 0.04)),
    ("cylinder_04", "cylinder", 700, _P(_cylinder_parts, 0.015, 0.18)),
    ("cylinder_05", "cylinder", 500, _P(_cylinder_parts, 0.025, 0.15)),

    ("bottle_00", "bottle", 450, _P(_bottle_parts, 0.033, 0.13, 0.04, 0.013, 0.02, 0.015, 0.015)),
    ("bottle_01", "bottle", 450, _P(_bottle_parts, 0.037, 0.14, 0.035, 0.014, 0.05, 0.015, 0.01)),
    ("bottle_02", "bottle", 700, _P(_bottle_parts, 0.022, 0.06, 0.01, 0.012, 0.008, 0.014, 0.015)),
    ("bottle_03", "bottle", 400, _P(_bottle_parts, 0.040, 0.08, 0.02, 0.025, 0.01, 0.027, 0.015)),
    ("bottle_04", "bottle", 500, _P(_bottle_parts, 0.025, 0.15, 0.03, 0.010, 0.03, 0.012, 0.012)),
    ("bottle_05", "bottle", 400, _P(_bottle_parts, 0.030, 0.12, 0.03, 0.012, 0.015, 0.014, 0.015,
                                    square=True)),

    ("sphere_00", "sphere", 900, _P(_sphere_parts, 0.020)),
    ("sphere_01", "sphere", 1100, _P(_sphere_parts, 0.025)),
    ("sphere_02", "sphere", 700, _P(_sphere_parts, 0.030)),
    ("sphere_03", "sphere", 500, _P(_sphere_parts, 0.040)),
    ("sphere_04", "sphere", 300, _P(_sphere_parts, 0.050)),
    ("sphere_05", "sphere", 700, _P(_sphere_parts, (0.045, 0.030, 0.025))),

    ("mug_00", "mug", 1000, _P(_mug_parts, 0.040, 0.095, 0.005, 0.008, 0.025, 0.030, 0.006)),
    ("mug_01", "mug", 1000, _P(_mug_parts, 0.035, 0.080, 0.004, 0.006, 0.022, 0.025, 0.005)),
    ("mug_02", "mug", 1000, _P(_mug_parts, 0.045, 0.075, 0.005, 0.008, 0.022, 0.022, 0.006)),
    ("mug_03", "mug", 1000, _P(_mug_parts, 0.030, 0.110, 0.004, 0.008, 0.022, 0.038, 0.0055)),
    ("mug_04", "mug", 1100, _P(_mug_parts, 0.028, 0.060, 0.004, 0.006, 0.016, 0.018, 0.004)),
    ("mug_05", "mug", 900, _P(_mug_parts, 0.042, 0.100, 0.006, 0.010, 0.028, 0.034, 0.007)),

    ("hammer_00", "hammer", 700, _P(_hammer_parts, 0.16, 0.025, 0.10, 0.028)),
    ("hammer_01", "hammer", 700, _P(_hammer_parts, 0.18, 0.028, 0.08, 0.030, claw=0.035, face=True)),
    ("hammer_02", "hammer", 600, _P(_hammer_parts, 0.14, 0.030, 0.09, 0.045)),
    ("hammer_03", "hammer", 800, _P(_hammer_parts, 0.10, 0.020, 0.06, 0.020, face=True)),
    ("hammer_04", "hammer", 700, _P(_hammer_parts, 0.20, 0.026, 0.09, 0.030, claw=0.04)),

    ("stamp_00", "stamp", 600, _P(_stamp_parts, (0.06, 0.04, 0.020), 0.010, 0.050, 0.016)),
    ("stamp_01", "stamp", 600, _P(_stamp_parts, (0.08, 0.05, 0.025), 0.012, 0.060, 0.018)),
    ("stamp_02", "stamp", 600, _P(_stamp_parts, (0.05, 0.05, 0.020), 0.009, 0.045, 0.014,
                                  round_block=True)),
    ("stamp_03", "stamp", 700, _P(_stamp_parts, (0.04, 0.04, 0.018), 0.008, 0.040, 0.013)),
    ("stamp_04", "stamp", 600, _P(_stamp_parts, (0.10, 0.03, 0.020), 0.011, 0.055, 0.017)),

    ("torus_00", "torus", 900, _P(_torus_parts, 0.040, 0.010)),
    ("torus_01", "torus", 900, _P(_torus_parts, 0.030, 0.008)),
    ("torus_02", "torus", 800, _P(_torus_parts, 0.050, 0.012)),
    ("torus_03", "torus", 700, _P(_torus_parts, 0.035, 0.015)),
    ("torus_04", "torus", 1000, _P(_torus_parts, 0.025, 0.0075)),
    ("torus_05", "torus", 900, _P(_torus_parts, 0.055, 0.009)),

    ("cone_00", "cone", 700, _P(_cone_parts, 0.030, 0.0, 0.08)),
    ("cone_01", "cone", 700, _P(_cone_parts, 0.040, 0.0, 0.06)),
    ("cone_02", "cone", 700, _P(_cone_parts, 0.035, 0.015, 0.07)),
    ("cone_03", "cone", 500, _P(_cone_parts, 0.020, 0.040, 0.09)),
    ("cone_04", "cone", 800, _P(_cone_parts, 0.020, 0.0, 0.12)),

    ("plate_00", "plate", 1000, _P(_plate_parts, 0.080, 0.080, 0.012)),
    ("plate_01", "plate", 1100, _P(_plate_parts, 0.065, 0.065, 0.010)),
    ("plate_02", "plate", 1100, _P(_plate_parts, 0.050, 0.050, 0.012)),
    ("plate_03", "plate", 1000, _P(_plate_parts, 0.055, 0.075, 0.015)),

    ("l_tool_00", "l_tool", 700, _P(_l_tool_parts, 0.15, 0.020, 0.08, 0.020, 0.015)),
    ("l_tool_01", "l_tool", 700, _P(_l_tool_parts, 0.12, 0.025, 0.12, 0.025, 0.012)),
    ("l_tool_02", "l_tool", 600, _P(_l_tool_parts, 0.18, 0.030, 0.06, 0.030, 0.020)),
    ("l_tool_03", "l_tool", 900, _P(_l_tool_parts, 0.10, 0.015, 0.05, 0.015, 0.012)),
    ("l_tool_04", "l_tool", 1200, _P(_l_tool_parts, 0.13, 0.0, 0.045, 0.0, 0.014, round_bar=True)),

    ("wineglass_00", "wineglass", 500, _P(_wineglass_parts, 0.035, 0.006, 0.005, 0.070,
                                          ((0.0, 0.008), (0.01, 0.024), (0.025, 0.035), (0.045, 0.040),
                                           (0.070, 0.038), (0.090, 0.033)))),
    ("wineglass_01", "wineglass", 500, _P(_wineglass_parts, 0.030, 0.006, 0.0045, 0.080,
                                          ((0.0, 0.006), (0.015, 0.020), (0.045, 0.026), (0.100, 0.024)))),
    ("wineglass_02", "wineglass", 300, _P(_wineglass_parts, 0.035, 0.006, 0.005, 0.080,
                                          ((0.0, 0.006), (0.060, 0.055)))),
    ("wineglass_03", "wineglass", 450, _P(_wineglass_parts, 0.040, 0.008, 0.008, 0.040,
                                          _spherical_bowl(0.045, 0.009))),
    ("wineglass_04", "wineglass", 400, _P(_wineglass_parts, 0.032, 0.006, 0.005, 0.060,
                                          ((0.0, 0.008), (0.010, 0.030), (0.022, 0.045), (0.035, 0.050)))),

    ("capsule_00", "capsule", 800, _P(_capsule_parts, 0.015, 0.06)),
    ("capsule_01", "capsule", 800, _P(_capsule_parts, 0.020, 0.08)),
    ("capsule_02", "capsule", 900, _P(_capsule_parts, 0.010, 0.10)),
    ("capsule_03", "capsule", 700, _P(_capsule_parts, 0.025, 0.05)),
    ("capsule_04", "capsule", 800, _P(_capsule_parts, 0.012, 0.16)),

    ("pyramid_00", "pyramid", 700, _P(_pyramid_parts, 4, 0.06 / np.sqrt(2), 0.06)),
    ("pyramid_01", "pyramid", 700, _P(_pyramid_parts, 4, 0.08 / np.sqrt(2), 0.05)),
    ("pyramid_02", "pyramid", 700, _P(_pyramid_parts, 3, 0.07 / np.sqrt(3), 0.06)),
    ("pyramid_03", "pyramid", 700, _P(_pyramid_parts, 4, 0.07 / np.sqrt(2), 0.05, 0.03 / np.sqrt(2))),
    ("pyramid_04", "pyramid", 700, _P(_pyramid_parts, 6, 0.04, 0.07)),
)

_HELD_OUT = frozenset({"box_04", "mug_03", "hammer_03", "torus_02", "wineglass_03"})

REGISTRY: dict[str, ObjectInfo] = {
    name: ObjectInfo(name, category, name in _HELD_OUT, float(density), builder)
    for name, category, density, builder in _TABLE
}
#: Every object's name, in registry order.
OBJECT_NAMES: tuple[str, ...] = tuple(REGISTRY)
CATEGORIES: tuple[str, ...] = tuple(dict.fromkeys(o.category for o in REGISTRY.values()))

_CATEGORY_RGBA: dict[str, tuple[float, float, float, float]] = {
    "box": (0.80, 0.55, 0.30, 1.0), "cube": (0.85, 0.25, 0.20, 1.0), "cylinder": (0.25, 0.55, 0.85, 1.0),
    "bottle": (0.30, 0.70, 0.45, 1.0), "sphere": (0.90, 0.75, 0.20, 1.0), "mug": (0.95, 0.95, 0.90, 1.0),
    "hammer": (0.45, 0.45, 0.50, 1.0), "stamp": (0.60, 0.35, 0.65, 1.0), "torus": (0.90, 0.45, 0.60, 1.0),
    "cone": (0.95, 0.50, 0.10, 1.0), "plate": (0.85, 0.85, 0.95, 1.0), "l_tool": (0.35, 0.35, 0.35, 1.0),
    "wineglass": (0.70, 0.85, 0.95, 1.0), "capsule": (0.40, 0.80, 0.80, 1.0), "pyramid": (0.75, 0.70, 0.45, 1.0),
}


class UnknownObjectError(AdadexError, KeyError):
    """Raised for a name that is not in :data:`REGISTRY`; the message suggests close names."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


def get_object(name: str) -> ObjectInfo:
    """The registry entry of object ``name``.

    Args:
        name: an object name (:data:`OBJECT_NAMES`).

    Raises:
        UnknownObjectError: ``name`` is not in the registry; the message suggests close names.
    """
    try:
        return REGISTRY[name]
    except (KeyError, TypeError):
        close = difflib.get_close_matches(str(name), OBJECT_NAMES, n=3, cutoff=0.6)
        hint = f"did you mean {', '.join(map(repr, close))}?" if close else "no close match."
        raise UnknownObjectError(
            f"unknown object {name!r}; {hint} ({len(REGISTRY)} objects exist, in categories "
            f"{', '.join(CATEGORIES)}; see adadex.sim.objects.OBJECT_NAMES)") from None


def held_out_objects() -> tuple[str, ...]:
    """Names of the unseen-object split, in registry order."""
    return tuple(n for n, o in REGISTRY.items() if o.held_out)


def object_split(name: str) -> str:
    """``"held_out"`` for an object of the unseen-object split (:func:`held_out_objects`), else ``"train"``."""
    return "held_out" if get_object(name).held_out else "train"


#: Most convex parts of any registry object (a test holds this to the registry).
MAX_OBJECT_PARTS = 21


def add_object_geoms(spec: mujoco.MjSpec, body: mujoco.MjsBody, name: str, *,
                     friction=(1.0, 0.01, 0.001), rgba=None, pad_to: int | None = None,
                     scale: float = 1.0) -> None:
    """Add object ``name`` to ``body``: one mesh asset and one collision geom per convex part.

    ``scale`` scales the object uniformly (domain randomization; mass follows the volume).
    ``pad_to`` adds (nearly) massless, non-colliding, invisible placeholder geoms up to that many geoms, so
    scenes with different objects have the same structure (equal ``MjModel.signature``) and can
    be stepped together as per-world models of one :class:`~adadex.sim.batched.BatchedSim`.

    Meshes are named ``{name}_part{i}`` and reused if ``spec`` already has them, so one object
    can sit on several bodies. Geoms are named ``{body.name}_{name}_part{i}`` (``{name}_part{i}``
    for an unnamed body). Mass and inertia come from the part volumes and the object's density;
    neighbouring parts overlap by slivers, so the MuJoCo mass exceeds :attr:`ObjectInfo.mass` by
    at most about 1 %.
    """
    info = get_object(name)
    color = list(rgba) if rgba is not None else list(_CATEGORY_RGBA[info.category])
    prefix = f"{body.name}_" if body.name else ""
    if not (np.isfinite(scale) and scale > 0):
        raise ConfigError(f"scale must be a positive number, got {scale}")
    for i, part in enumerate(_parts(info)):
        mesh_name = f"{name}_part{i}" if scale == 1.0 else f"{name}_x{scale:.4f}_part{i}"
        if spec.mesh(mesh_name) is None:
            spec.add_mesh(name=mesh_name, uservert=(scale * part.vertices).flatten(), userface=part.faces.flatten(),
                          inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_EXACT)
        body.add_geom(name=f"{prefix}{mesh_name}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh_name,
                      density=info.density, condim=4, friction=list(friction), contype=1,
                      conaffinity=1, rgba=color)
    n = len(_parts(info))
    if pad_to is not None and pad_to < n:
        raise ConfigError(f"pad_to={pad_to} is less than the {n} parts of {name!r}")
    for i in range(n, pad_to or 0):
        # Placeholders are meshes with a mesh asset each: the model structure counts geom types and meshes.
        if spec.mesh(f"adadex_pad{i}") is None:
            spec.add_mesh(name=f"adadex_pad{i}", uservert=[0, 0, 0, 1e-3, 0, 0, 0, 1e-3, 0, 0, 0, 1e-3])
        # The first placeholder carries 1 mg 1 cm off-centre (moving the centre of mass by ~0.1 µm), so no
        # object body is "simple" (inertia frame = body frame): MuJoCo sizes the sparse inertia differently
        # for simple bodies, and worlds stepped together must agree on that too.
        body.add_geom(name=f"{prefix}{name}_pad{i}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"adadex_pad{i}",
                      mass=1e-6 if i == n else 0.0, pos=[0.01, 0.01, 0.01] if i == n else [0, 0, 0],
                      contype=0, conaffinity=0, group=5, rgba=[0, 0, 0, 0])
