"""Procedural outdoor city: the outdoor counterpart of the demo room, labelled in cityscapes19.

The city is a grid of ``blocks_x x blocks_y`` square blocks of edge ``block_size`` metres, z up,
block (bx, by) spanning ``[bx B, (bx+1) B] x [by B, (by+1) B]``. Each block owns the street on its
low-x and low-y sides (``road_width``: parked cars, motorcycles, trucks, buses, cyclists in the
parking lanes) and a lot raised by a curb: a sidewalk ring (street trees, street lights, traffic
lights and signs, people, parked bicycles) around parcels holding buildings (windows and doors
protrude from the facades and are ``building``, as Cityscapes labels them; garden walls, fences,
hedges, trees in the yard) or parks (trees, fences, people on the grass). Trees are a trunk and a
convex crown, both ``vegetation``. ``sky`` is never a point: it is what frames see above the
horizon where nothing is hit.

Everything of a block is drawn from its own generator, seeded by (seed, bx, by), and stays inside
its cell (tree crowns overhang the street by a little), so a block is the same whatever the
extent of the city. The cloud is sampled block by block (:func:`block_points`: each block's mesh
and its ray caster exist only while it is sampled). The frames (``drone_views`` nadir and oblique
views at ``drone_height`` and ``street_views`` along the block's streets at ``street_height`` per
block) are a :class:`~diffuser_lab.data.frames.LazyFrames`: a frame is rendered when it is read,
by a ray caster over the blocks within ``view_distance`` of its block (cached for the frames of
that block, block meshes kept in a small LRU), and its depth is cut at ``view_distance``, so a
frame is the same whatever the extent too. Memory follows a block neighbourhood and a frame, plus
the cloud itself.
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from diffuser_lab import progress, seeding
from diffuser_lab.config import SceneConfig, Section, at_least, check, key, rule, within
from diffuser_lab.data.frames import LazyFrames
from diffuser_lab.data.mapping import load_mapping, shipped_mappings
from diffuser_lab.data.render import MeshRenderer, intrinsics, look_at, sample_surface
from diffuser_lab.data.scene import IGNORE, Frame, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel

__all__ = ["CityOptions", "CITYSCAPES19", "City", "block_mesh", "make_city_scene", "load", "frames"]


@dataclass
class CityOptions(Section):
    """Procedural outdoor city (diffuser_lab.data.sources.city): a grid of blocks, each built from
    its own seed (seed, bx, by), labelled in cityscapes19; drone and street-level views rendered
    per frame on access from the blocks around the camera."""

    KEY = "scene.options"
    seed: int = 0
    blocks_x: int = key(2, within(1, 1000, steps=True))  # blocks along x (the city's extent)
    blocks_y: int = key(2, within(1, 1000, steps=True))  # blocks along y
    block_size: float = key(60.0, within(30, 500, "metres"))  # edge of a block (street + lot), metres
    road_width: float = key(10.0, within(6, 30, "metres"))  # street on each block's low x / low y side
    sidewalk_width: float = key(3.0, within(1.5, 10, "metres"))
    point_spacing: float = key(0.2, within(0.01, 2.0, "metres"))  # metres between sampled surface points (~250k a block at 0.2)
    point_noise: float = key(0.01, at_least(0))  # std of gaussian position noise, metres
    drone_views: int = key(4, at_least(0))  # per block: nadir and oblique views from drone_height
    street_views: int = key(4, at_least(0))  # per block: views from street_height along its streets
    drone_height: List[float] = key(check=rule("min <= max, both > 30 m (above the roofs)",
                                               lambda v: len(v) == 2 and 30 < v[0] <= v[1]),
                                    factory=lambda: [40.0, 70.0])  # metres above the road
    street_height: List[float] = key(check=rule("0.5 m <= min <= max <= 5 m",
                                                lambda v: len(v) == 2 and 0.5 <= v[0] <= v[1] <= 5),
                                     factory=lambda: [1.5, 2.0])  # metres above the road
    view_distance: float = key(150.0, within(20, 2000, "metres"))  # frames see up to this far (depth 0 beyond)
    image_width: int = 320
    image_height: int = 240
    fov_deg: float = key(70.0, within(10, 150))  # horizontal field of view
    sky: bool = True  # label images: pixels looking up at nothing are sky (depth 0), else IGNORE

    def _check_keys(self) -> None:
        check(self.image_width >= 16 and self.image_height >= 16, "scene.options.image_width/height",
               (self.image_width, self.image_height), ">= 16 pixels")
        check(self.road_width + 2 * self.sidewalk_width + 10 <= self.block_size, "scene.options.block_size",
               self.block_size, ">= road_width + 2 sidewalk_width + 10 m (room for a lot)")
        check(self.drone_views == 0 or self.view_distance > self.drone_height[1], "scene.options.view_distance",
               self.view_distance, "> drone_height max (a drone view sees the ground)")


CITYSCAPES19 = Taxonomy(
    name="cityscapes19",
    names=("road", "sidewalk", "building", "wall", "fence", "pole", "traffic light", "traffic sign", "vegetation",
           "terrain", "sky", "person", "rider", "car", "truck", "bus", "train", "motorcycle", "bicycle"),
    colors=np.array([[128, 64, 128], [244, 35, 232], [70, 70, 70], [102, 102, 156], [190, 153, 153],
                     [153, 153, 153], [250, 170, 30], [220, 220, 0], [107, 142, 35], [152, 251, 152],
                     [70, 130, 180], [220, 20, 60], [255, 0, 0], [0, 0, 142], [0, 0, 70], [0, 60, 100],
                     [0, 80, 100], [0, 0, 230], [119, 11, 32]], np.uint8))
"""The shipped cityscapes19 taxonomy (data/taxonomies/cityscapes19.csv; data/taxonomy.py imports the
sources, so the city holds its own copy, checked equal by its tests)."""
_C = {n: i for i, n in enumerate(CITYSCAPES19.names)}
_LIFT = 0.005  # m, objects stand this far above the surface they are on (hidden faces are dropped)
_CURB = 0.15  # m, the lot (sidewalk, terrain) above the road

_SIGNS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64) - 0.5
_BOX_TRIS = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                      [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])


def _outward(v: np.ndarray, t: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Triangles ``t`` of a convex solid with vertices ``v`` wound so their normals leave ``centre``."""
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    flip = np.einsum("tk,tk->t", n, v[t].mean(1) - centre) < 0
    t = t.copy()
    t[flip] = t[flip][:, ::-1]
    return t


_UNIT_BOX = _outward(_SIGNS, _BOX_TRIS, np.zeros(3))


def _unit_sphere_hull(n: int = 26) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) near-uniform unit directions and the outward triangles of their convex hull."""
    from scipy.spatial import ConvexHull

    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z ** 2)
    phi = np.pi * (1.0 + 5 ** 0.5) * i
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    return d, _outward(d, ConvexHull(d).simplices, np.zeros(3))


_SPHERE_DIRS, _SPHERE_TRIS = _unit_sphere_hull()


class _Mesh:
    """Closed, outward-wound boxes, convex crowns and one-sided quads of one block, in world metres."""

    def __init__(self, origin: np.ndarray):
        self.origin = np.array([origin[0], origin[1], 0.0])
        self.v: list[np.ndarray] = []
        self.t: list[np.ndarray] = []
        self.lab: list[np.ndarray] = []
        self.nv = 0

    def _add(self, v, t, label):
        self.v.append(v + self.origin)
        self.t.append(t + self.nv)
        self.lab.append(np.full(len(t), label, np.int16))
        self.nv += len(v)

    def box(self, centre, size, label, yaw=0.0):
        """A box of ``size`` (along, across, height) centred at ``centre`` (local metres), turned by yaw."""
        c, s = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self._add(np.asarray(centre, float) + (_SIGNS * np.asarray(size, float)) @ R.T, _UNIT_BOX, _C[label])

    def standing(self, pos, yaw, z0, parts):
        """Parts ((along, across, z from the base), size, label) of an object at ``pos`` on height z0."""
        c, s = math.cos(yaw), math.sin(yaw)
        for (a, b, z), size, label in parts:  # a handful of parts
            self.box((pos[0] + c * a - s * b, pos[1] + s * a + c * b, z0 + _LIFT + z), size, label, yaw)

    def crown(self, centre, radii, label, rng):
        d = _SPHERE_DIRS * rng.uniform(0.85, 1.15, (len(_SPHERE_DIRS), 1))
        self._add(np.asarray(centre, float) + d * np.asarray(radii, float), _SPHERE_TRIS, _C[label])

    def quad(self, corners, label):
        """A one-sided quad facing +z when its corners run counter-clockwise seen from above, or
        facing the side its corner order says (right-hand rule)."""
        self._add(np.asarray(corners, float), np.array([[0, 1, 2], [0, 2, 3]]), _C[label])

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (np.concatenate(self.v).astype(np.float32), np.concatenate(self.t).astype(np.int32),
                np.concatenate(self.lab))


def _rect(x0, y0, x1, y1, z):
    return [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)]


# ---------------------------------------------------------------- objects (local parts, z from the base)

def _car(rng):
    ln, wd = rng.uniform(3.9, 4.8), rng.uniform(1.7, 1.9)
    hb, hc = rng.uniform(0.65, 0.8), rng.uniform(0.55, 0.7)
    parts = [((0, 0, 0.3 + hb / 2), (ln, wd, hb), "car"),
             ((-0.05 * ln, 0, 0.3 + hb + hc / 2), (0.55 * ln, wd - 0.15, hc), "car")]
    parts += [((sx * ln * 0.32, sy * (wd / 2 - 0.12), 0.3), (0.62, 0.22, 0.6), "car")
              for sx in (-1, 1) for sy in (-1, 1)]
    return parts, ln


def _truck(rng):
    ln, cargo, h = rng.uniform(6.5, 8.5), rng.uniform(4.5, 5.5), rng.uniform(3.0, 3.6)
    return [((ln / 2 - 1.1, 0, 0.5 + 1.1), (2.2, 2.3, 2.2), "truck"),
            ((ln / 2 - 2.3 - cargo / 2, 0, 0.55 + h / 2), (cargo, 2.45, h), "truck"),
            ((0, 0, 0.35), (ln - 0.4, 1.6, 0.7), "truck")], ln


def _bus(rng):
    ln = rng.uniform(11.0, 12.5)
    return [((0, 0, 0.35 + 1.5), (ln, 2.5, 3.0), "bus"),
            ((0, 0, 0.2), (ln - 1.5, 2.0, 0.4), "bus")], ln


def _two_wheeler(label, ln, h):
    return [((sx * ln * 0.33, 0, 0.33), (0.62, 0.08, 0.64), label) for sx in (-1, 1)] + \
           [((0, 0, h * 0.7), (ln * 0.6, 0.14 if label == "bicycle" else 0.35, h * 0.35), label)]


def _person(rng, label="person", z=0.0):
    h = rng.uniform(1.55, 1.9)
    return [((0, 0, z + 0.45 * h / 2), (0.3, 0.36, 0.45 * h), label),
            ((0, 0, z + 0.45 * h + 0.2 * h), (0.26, 0.44, 0.4 * h), label),
            ((0, 0, z + 0.85 * h + 0.075 * h), (0.2, 0.2, 0.15 * h), label)]


def _tree(m: _Mesh, pos, z0, rng, scale=1.0):
    ht, r = rng.uniform(1.8, 3.5) * scale, rng.uniform(1.4, 3.0) * scale
    m.box((pos[0], pos[1], z0 + _LIFT + ht / 2 + 0.2), (0.3, 0.3, ht + 0.4), "vegetation")
    m.crown((pos[0], pos[1], z0 + ht + 0.8 * r), (r, r, 1.1 * r), "vegetation", rng)
    return r


def _pole(m: _Mesh, pos, yaw, z0, rng, kind):
    """A street light (pole), a traffic light on its pole, or a traffic sign on its pole."""
    if kind == "light":
        h = rng.uniform(6.0, 8.0)
        m.standing(pos, yaw, z0, [((0, 0, h / 2), (0.18, 0.18, h), "pole"),
                                  ((0, -0.75, h - 0.1), (0.1, 1.5, 0.1), "pole"),
                                  ((0, -1.4, h - 0.25), (0.35, 0.5, 0.2), "pole")])
    elif kind == "traffic light":
        h = rng.uniform(3.2, 3.8)
        m.standing(pos, yaw, z0, [((0, 0, h / 2), (0.14, 0.14, h), "pole"),
                                  ((0, -0.2, h + 0.45), (0.35, 0.3, 0.95), "traffic light")])
    else:
        h = rng.uniform(2.2, 2.8)
        m.standing(pos, yaw, z0, [((0, 0, h / 2), (0.08, 0.08, h), "pole"),
                                  ((0, -0.07, h + 0.3), (0.7, 0.05, 0.7), "traffic sign")])


def _building(m: _Mesh, x0, y0, x1, y1, z0, rng):
    """A box with a grid of protruding windows on each facade, a door, sometimes a roof structure."""
    h = rng.uniform(8.0, 25.0)
    cx, cy, lx, ly = (x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0
    m.box((cx, cy, z0 + _LIFT + h / 2), (lx, ly, h), "building")
    floor_h, col = rng.uniform(3.0, 3.6), rng.uniform(2.6, 3.6)
    ww, wh = rng.uniform(0.9, 1.5), rng.uniform(1.2, 1.7)
    door_side = int(rng.integers(4))
    # facades: (centre of the facade line, along unit, outward unit, length)
    facades = [((cx, y0), (1, 0), (0, -1), lx), ((x1, cy), (0, 1), (1, 0), ly),
               ((cx, y1), (-1, 0), (0, 1), lx), ((x0, cy), (0, -1), (-1, 0), ly)]
    for k, (c, a, o, length) in enumerate(facades):  # 4 facades
        a, o = np.array(a, float), np.array(o, float)
        yaw = math.atan2(a[1], a[0])
        n_col = int((length - 1.0) // col)
        n_floor = int((h - 1.0) // floor_h)
        door_col = int(rng.integers(max(n_col, 1))) if k == door_side else -1
        for j in range(n_col):
            s = (j - (n_col - 1) / 2) * col
            for f in range(n_floor):
                p = np.array(c) + a * s
                if f == 0 and j == door_col:
                    m.box((p[0], p[1], z0 + _LIFT + 1.15), (1.4, 0.16, 2.3), "building", yaw)
                elif rng.random() < 0.92:
                    zc = z0 + f * floor_h + 0.9 + wh / 2
                    m.box((p[0], p[1], zc), (ww, 0.12, wh), "building", yaw)
    if rng.random() < 0.4:  # a roof structure (stair house, machinery)
        m.box((cx + rng.uniform(-0.2, 0.2) * lx, cy + rng.uniform(-0.2, 0.2) * ly, z0 + h + 1.2),
              (rng.uniform(2, 5), rng.uniform(2, 5), 2.4), "building")


def _barrier(m: _Mesh, p0, p1, z0, label, rng):
    """A garden wall (``wall``) or a fence panel (``fence``) from p0 to p1 (local xy)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    length = float(np.hypot(*d))
    if length < 1.0:
        return
    h, th = (rng.uniform(1.0, 2.0), 0.3) if label == "wall" else (rng.uniform(1.1, 1.8), 0.06)
    c = (p0 + p1) / 2
    m.box((c[0], c[1], z0 + _LIFT + h / 2), (length, th, h), label, math.atan2(d[1], d[0]))


# ---------------------------------------------------------------- a block

def block_mesh(cfg: CityOptions, bx: int, by: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The labelled triangle mesh of block (bx, by): vertices (V, 3) float32 world metres, triangles
    (T, 3) int32 wound outward, triangle labels (T,) int16 cityscapes19 ids. Drawn from the
    generator seeded by (seed, bx, by) alone."""
    rng = seeding.keyed("city.block", cfg.seed, bx, by, 0)
    B, w, s = cfg.block_size, cfg.road_width, cfg.sidewalk_width
    m = _Mesh(np.array([bx * B, by * B]))
    zt = _CURB
    # the streets on the low sides and the raised lot: sidewalk ring, curbs, inner terrain
    m.quad(_rect(0, 0, w, B, 0.0), "road")
    m.quad(_rect(w, 0, B, w, 0.0), "road")
    a, b = w + s, B - s
    for r in (_rect(w, w, B, a, zt), _rect(w, b, B, B, zt), _rect(w, a, a, b, zt), _rect(b, a, B, b, zt)):
        m.quad(r, "sidewalk")
    m.quad(_rect(a, a, b, b, zt), "terrain")
    for p, q in (((w, w), (B, w)), ((B, w), (B, B)), ((B, B), (w, B)), ((w, B), (w, w))):  # curbs, outward
        m.quad([(*p, 0.0), (*q, 0.0), (*q, zt), (*p, zt)], "sidewalk")

    _street(m, cfg, rng)
    _sidewalks(m, cfg, rng, zt)
    _parcels(m, cfg, rng, zt)
    return m.arrays()


def _street(m: _Mesh, cfg: CityOptions, rng):
    """Parking lanes along both kerbs of the block's two streets: vehicles, cyclists."""
    B, w = cfg.block_size, cfg.road_width
    lanes = []  # (start point, along unit, across offset of the lane centre, length)
    for off in (1.25, w - 1.25):
        lanes.append(((off, w + 1.0), (0.0, 1.0), B - w - 2.0))  # the low-x street, along y
        lanes.append(((w + 1.0, off), (1.0, 0.0), B - w - 2.0))  # the low-y street, along x
    for (x0, y0), (ax, ay), length in lanes:
        pos = rng.uniform(0.0, 4.0)
        while pos < length:
            u = rng.random()
            if u < 0.3:
                pos += rng.uniform(4.0, 12.0)  # an empty stretch
                continue
            yaw = math.atan2(ay, ax) + (math.pi if rng.random() < 0.5 else 0.0)
            if u < 0.82:
                parts, ln = _car(rng)
            elif u < 0.87:
                parts, ln = _truck(rng)
            elif u < 0.90:
                parts, ln = _bus(rng)
            elif u < 0.95:
                parts, ln = _two_wheeler("motorcycle", 2.0, 1.1), 2.0
            else:  # a cyclist: a rider on a bicycle
                parts, ln = _two_wheeler("bicycle", 1.75, 0.9) + _person(rng, "rider", z=0.55), 1.75
            if pos + ln > length:
                break
            c = pos + ln / 2
            m.standing((x0 + ax * c, y0 + ay * c), yaw, 0.0, parts)
            pos += ln + rng.uniform(0.8, 3.0)


def _sidewalks(m: _Mesh, cfg: CityOptions, rng, zt):
    """Street trees, lights, signs, bicycles and people on the four sides of the sidewalk ring;
    traffic lights on some corners."""
    B, w, s = cfg.block_size, cfg.road_width, cfg.sidewalk_width
    sides = [((w, w), (1, 0), (0, 1)), ((B, w), (0, 1), (-1, 0)),
             ((B, B), (-1, 0), (0, -1)), ((w, B), (0, -1), (1, 0))]  # curb start, along, inward
    length = B - w
    for (ox, oy), (ax, ay), (nx, ny) in sides:
        taken: list[tuple[float, float]] = []

        def put(along, radius):
            if along - radius < 1.0 or along + radius > length - 1.0:
                return False
            if any(abs(along - p) < radius + r for p, r in taken):
                return False
            taken.append((along, radius))
            return True

        def at(along, inward):
            return ox + ax * along + nx * inward, oy + ay * along + ny * inward

        yaw = math.atan2(ay, ax)
        spacing = rng.uniform(9.0, 15.0)
        for t in np.arange(rng.uniform(3.0, spacing), length - 2.0, spacing):  # street trees
            if rng.random() < 0.8 and put(t, 1.0):
                _tree(m, at(t, min(1.1, s / 2)), zt, rng, scale=0.9)
        for t in np.arange(rng.uniform(5.0, 15.0), length - 2.0, rng.uniform(20.0, 30.0)):  # street lights
            if put(t, 0.5):
                _pole(m, at(t, 0.45), yaw, zt, rng, "light")
        for _ in range(int(rng.integers(0, 3))):
            t = rng.uniform(2.0, length - 2.0)
            if put(t, 0.5):
                _pole(m, at(t, 0.45), yaw + math.pi / 2, zt, rng, "sign")
        for _ in range(int(rng.poisson(3.0))):  # people walking
            t = rng.uniform(2.0, length - 2.0)
            if put(t, 0.5):
                m.standing(at(t, rng.uniform(1.3, max(1.4, s - 0.5))), rng.uniform(0, 2 * np.pi), zt,
                           _person(rng))
        if rng.random() < 0.5:  # parked bicycles
            t = rng.uniform(3.0, length - 3.0)
            for k in range(int(rng.integers(1, 4))):
                if put(t + 0.7 * k, 0.35):
                    m.standing(at(t + 0.7 * k, s - 0.5), yaw + math.pi / 2, zt, _two_wheeler("bicycle", 1.7, 0.9))
    for (cx, cy), yaw in (((w + 0.5, w + 0.5), 0.25 * np.pi), ((B - 0.5, w + 0.5), 0.75 * np.pi),
                          ((w + 0.5, B - 0.5), -0.25 * np.pi)):  # corners next to an intersection
        if rng.random() < 0.6:
            _pole(m, (cx, cy), yaw, zt, rng, "traffic light")


def _parcels(m: _Mesh, cfg: CityOptions, rng, zt):
    """The inner lot cut into 1-4 parcels, each a building with its yard or a park."""
    B, w, s = cfg.block_size, cfg.road_width, cfg.sidewalk_width
    a, b = w + s, B - s
    L = b - a

    def cuts():
        n = 2 if L > 30 and rng.random() < 0.7 else 1
        return [a, a + L * rng.uniform(0.35, 0.65), b] if n == 2 else [a, b]

    xs, ys = cuts(), cuts()
    parcels = [(xs[i], ys[j], xs[i + 1], ys[j + 1]) for i in range(len(xs) - 1) for j in range(len(ys) - 1)]
    built = int(rng.integers(len(parcels)))  # every block has a building (where a parcel is big enough)
    for k, (x0, y0, x1, y1) in enumerate(parcels):
        if min(x1 - x0, y1 - y0) >= 12.0 and (k == built or rng.random() < 0.6):
            _yard(m, x0, y0, x1, y1, zt, rng)
        else:
            _park(m, x0, y0, x1, y1, zt, rng)


def _yard(m: _Mesh, x0, y0, x1, y1, zt, rng):
    sb = rng.uniform(0.5, 5.0, 4)  # setbacks: low y, high x, high y, low x
    bx0, by0, bx1, by1 = x0 + sb[3], y0 + sb[0], x1 - sb[1], y1 - sb[2]
    _building(m, bx0, by0, bx1, by1, zt, rng)
    edges = [((x0 + 0.3, y0 + 0.3), (x1 - 0.3, y0 + 0.3)), ((x1 - 0.3, y0 + 0.3), (x1 - 0.3, y1 - 0.3)),
             ((x1 - 0.3, y1 - 0.3), (x0 + 0.3, y1 - 0.3)), ((x0 + 0.3, y1 - 0.3), (x0 + 0.3, y0 + 0.3))]
    for k, (p, q) in enumerate(edges):  # a garden wall, a fence or a hedge where the yard is deep enough
        if sb[k] < 2.0:
            continue
        u = rng.random()
        if u < 0.3:
            _barrier(m, p, q, zt, "wall", rng)
        elif u < 0.6:
            _barrier(m, p, q, zt, "fence", rng)
        elif u < 0.8:
            d = np.subtract(q, p)
            c = (np.add(p, q)) / 2
            h = rng.uniform(0.8, 1.6)
            m.box((c[0], c[1], zt + _LIFT + h / 2), (np.hypot(*d) - 0.6, 0.8, h), "vegetation", math.atan2(d[1], d[0]))
        if sb[k] > 4.0 and rng.random() < 0.6:  # a tree in the yard
            t = rng.uniform(0.25, 0.75)
            inward = {0: (0, 1), 1: (-1, 0), 2: (0, -1), 3: (1, 0)}[k]
            pos = np.add(p, np.subtract(q, p) * t) + np.multiply(inward, sb[k] / 2)
            _tree(m, pos, zt, rng, scale=0.7)


def _park(m: _Mesh, x0, y0, x1, y1, zt, rng):
    area = (x1 - x0) * (y1 - y0)
    trees: list[tuple[float, float]] = []
    for _ in range(int(area / 25)):  # rejection-sampled tree spots, >= 5 m apart
        p = rng.uniform([x0 + 3.5, y0 + 3.5], [x1 - 3.5, y1 - 3.5]) if min(x1 - x0, y1 - y0) > 7 else None
        if p is None:
            break
        if all(np.hypot(p[0] - q[0], p[1] - q[1]) > 5.5 for q in trees):
            trees.append((p[0], p[1]))
            if len(trees) >= area / 60:
                break
    for p in trees:
        _tree(m, p, zt, rng)
    for _ in range(int(rng.poisson(1.5))):  # people on the grass, away from the trunks
        p = rng.uniform([x0 + 1.0, y0 + 1.0], [x1 - 1.0, y1 - 1.0])
        if all(np.hypot(p[0] - q[0], p[1] - q[1]) > 1.0 for q in trees):
            m.standing(p, rng.uniform(0, 2 * np.pi), zt, _person(rng))
    if rng.random() < 0.5:  # a fence around the park
        c = [(x0 + 0.3, y0 + 0.3), (x1 - 0.3, y0 + 0.3), (x1 - 0.3, y1 - 0.3), (x0 + 0.3, y1 - 0.3)]
        for k in range(4):
            _barrier(m, c[k], c[(k + 1) % 4], zt, "fence", rng)


def block_points(cfg: CityOptions, bx: int, by: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (N, 3) float32, normals (N, 3) float32 and labels (N,) int16 sampled on block (bx, by)
    every ``point_spacing`` metres (covered surfaces dropped), seeded by (seed, bx, by)."""
    v, t, lab = block_mesh(cfg, bx, by)
    renderer = MeshRenderer(v, t, lab)
    return sample_surface(v, t, lab, cfg.point_spacing, (cfg.seed, bx, by), noise=cfg.point_noise, renderer=renderer)


# ---------------------------------------------------------------- views

def block_poses(cfg: CityOptions, bx: int, by: int) -> list[tuple[str, np.ndarray]]:
    """The (kind, T_cw) of block (bx, by)'s views: ``street_views`` along its two streets at
    ``street_height``, ``drone_views`` alternately nadir and oblique (30-60 degrees down) from
    ``drone_height``, every eye above the block's own cell. Seeded by (seed, bx, by)."""
    rng = seeding.keyed("city.views", cfg.seed, bx, by, 2)
    B, w = cfg.block_size, cfg.road_width
    o = np.array([bx * B, by * B, 0.0])
    out = []
    for k in range(cfg.street_views):
        along = rng.uniform(w + 2.0, B - 2.0)
        across = w / 2 + rng.uniform(-0.5, 0.5)
        h = rng.uniform(*cfg.street_height)
        heading = (math.pi / 2 if k % 2 == 0 else 0.0) + (math.pi if rng.random() < 0.5 else 0.0)
        heading += np.deg2rad(rng.uniform(-25, 25))
        pitch = np.deg2rad(rng.uniform(-12, 2))
        eye = o + (np.array([across, along, h]) if k % 2 == 0 else np.array([along, across, h]))
        fwd = np.array([math.cos(heading) * math.cos(pitch), math.sin(heading) * math.cos(pitch), math.sin(pitch)])
        out.append(("street", look_at(eye, eye + fwd)))
    for k in range(cfg.drone_views):
        h = rng.uniform(*cfg.drone_height)
        eye = o + np.array([*rng.uniform(0.15 * B, 0.85 * B, 2), h])
        heading = rng.uniform(0, 2 * np.pi)
        pitch = np.deg2rad(rng.uniform(80, 90) if k % 2 == 0 else rng.uniform(30, 60))
        fwd = np.array([math.cos(heading) * math.cos(pitch), math.sin(heading) * math.cos(pitch), -math.sin(pitch)])
        up = (math.cos(heading), math.sin(heading), 0.0) if k % 2 == 0 else (0.0, 0.0, 1.0)
        out.append(("nadir" if k % 2 == 0 else "oblique", look_at(eye, eye + fwd, up=up)))
    return out


class City:
    """The city of ``cfg``: block meshes on demand (an LRU of ``cache_blocks``) and a ray caster per
    block neighbourhood (the last one kept), for rendering its frames lazily."""

    def __init__(self, cfg: CityOptions, sensor: Optional[SensorModel] = None):
        self.cfg = cfg
        self.sensor = sensor
        self.reach = int(math.ceil((cfg.view_distance + 5.0) / cfg.block_size))
        side = 2 * self.reach + 1
        self.cache_blocks = side * side + side
        self._meshes: OrderedDict = OrderedDict()
        self._renderer: tuple[Optional[tuple[int, int]], Optional[MeshRenderer]] = (None, None)
        self.K = intrinsics(cfg.image_width, cfg.image_height, cfg.fov_deg)
        self._lock = threading.Lock()  # frames read ahead on several threads share the caches below
        self.views: list[tuple[str, int, int, np.ndarray]] = []  # (name, bx, by, T_cw)
        for bx in range(cfg.blocks_x):
            for by in range(cfg.blocks_y):
                for k, (kind, T) in enumerate(block_poses(cfg, bx, by)):
                    self.views.append((f"b{bx:03d}_{by:03d}_{k:02d}_{kind}", bx, by, T))

    def mesh(self, bx: int, by: int):
        key = (bx, by)
        if key in self._meshes:
            self._meshes.move_to_end(key)
            return self._meshes[key]
        out = self._meshes[key] = block_mesh(self.cfg, bx, by)
        while len(self._meshes) > self.cache_blocks:
            self._meshes.popitem(last=False)
        return out

    def renderer(self, bx: int, by: int) -> MeshRenderer:
        """The ray caster over the blocks within ``reach`` of (bx, by) that the city has."""
        if self._renderer[0] == (bx, by):
            return self._renderer[1]
        self._renderer = (None, None)  # drop the old one before building the next
        r, c = self.reach, self.cfg
        parts = [self.mesh(i, j) for i in range(max(bx - r, 0), min(bx + r, c.blocks_x - 1) + 1)
                 for j in range(max(by - r, 0), min(by + r, c.blocks_y - 1) + 1)]
        offs = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
        v = np.concatenate([p[0] for p in parts])
        t = np.concatenate([p[1] + o for p, o in zip(parts, offs)])
        lab = np.concatenate([p[2] for p in parts])
        self._renderer = ((bx, by), MeshRenderer(v, t, lab))
        return self._renderer[1]

    def frame(self, i: int) -> Frame:
        """View i rendered: z-depth (0 = no hit or beyond ``view_distance``), cityscapes19 labels
        (``sky`` where a ray looking up hits nothing, with ``cfg.sky``; IGNORE where there is no depth)."""
        with self._lock:  # the block meshes and the ray caster are one cache (open3d casts on every core)
            return self._frame(i)

    def _frame(self, i: int) -> Frame:
        name, bx, by, T = self.views[i]
        c = self.cfg
        rend = self.renderer(bx, by)
        if self.sensor is None:
            depth, labels = rend.render(self.K, T, c.image_width, c.image_height)
            normals = None
        else:
            depth, labels, normals = rend.render_with_normals(self.K, T, c.image_width, c.image_height)
        u, v = np.meshgrid(np.arange(c.image_width), np.arange(c.image_height))
        ray = np.stack([(u - self.K[0, 2]) / self.K[0, 0], (v - self.K[1, 2]) / self.K[1, 1],
                        np.ones(u.shape)], axis=-1)  # camera rays with unit z
        far = depth * np.linalg.norm(ray, axis=-1) > c.view_distance
        depth[far] = 0.0
        labels[far] = IGNORE
        if c.sky:
            up = (ray @ T[:3, :3])[..., 2] > 0  # world z of each ray
            labels[(labels == IGNORE) & ~far & up] = _C["sky"]
        if self.sensor is not None:
            depth = self.sensor.apply(depth, self.K, i, normals=normals)
        return Frame(name=name, K=self.K.copy(), T_cw=T.copy(), depth=depth, labels=None, gt_labels=labels)


def make_city_scene(cfg: CityOptions, sensor: Optional[SensorModel] = None) -> tuple[Scene, City]:
    """The city of ``cfg``: points sampled block by block (normals the exact mesh normals,
    cityscapes19 ground truth) and its frames, rendered when read. Returns the scene and the
    :class:`City` that renders them."""
    city = City(cfg, sensor)
    pts, nrm, lab = [], [], []
    n = cfg.blocks_x * cfg.blocks_y
    with progress.stage(f"sampling the city's blocks ({n})", total=n, unit="block") as bar:
        for bx in range(cfg.blocks_x):
            for by in range(cfg.blocks_y):
                p, q, r = block_points(cfg, bx, by)
                pts.append(p)
                nrm.append(q)
                lab.append(r)
                bar.update()
    points = np.concatenate(pts)
    del pts
    normals = np.concatenate(nrm)
    del nrm
    frames = LazyFrames([v[0] for v in city.views], city.frame, poses=[v[3] for v in city.views])
    scene = Scene(name=f"city_seed{cfg.seed}_{cfg.blocks_x}x{cfg.blocks_y}", points=points, taxonomy=CITYSCAPES19,
                  frames=frames, normals=normals, gt_labels=np.concatenate(lab))
    return scene, city


def _lut(taxonomy: Taxonomy) -> Optional[np.ndarray]:
    """None when ``taxonomy`` is cityscapes19, else the shipped ``cityscapes19_to_<name>`` lookup."""
    if taxonomy.name == CITYSCAPES19.name:
        return None
    name = f"{CITYSCAPES19.name}_to_{taxonomy.name}"
    if name not in shipped_mappings():
        raise ValueError(f"scene=city is labelled in cityscapes19 and no shipped mapping {name} moves it to "
                         f"taxonomy={taxonomy.name}: run it with taxonomy=cityscapes19")
    return load_mapping(name, taxonomy).lut


def _moved(lut: np.ndarray, ids: np.ndarray) -> np.ndarray:
    return np.where(ids == IGNORE, IGNORE, lut[np.maximum(ids, 0)]).astype(np.int16)


def _frames_in(frames: LazyFrames, lut: Optional[np.ndarray]) -> LazyFrames:
    if lut is None:
        return frames
    return LazyFrames.mapped(frames, lambda i, f: Frame(f.name, f.K, f.T_cw, f.depth, gt_labels=_moved(lut, f.gt_labels)))


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=city``: the city of the ``scene.options`` keys (defaults when unset), in ``taxonomy``
    (cityscapes19, or one a shipped ``cityscapes19_to_<name>`` mapping reaches)."""
    lut = _lut(taxonomy)
    scene, _ = make_city_scene(cfg.options, sensor)
    if lut is None:
        scene.taxonomy = taxonomy
        return scene
    return Scene(scene.name, scene.points, taxonomy, _frames_in(scene.frames, lut), scene.normals,
                 gt_labels=_moved(lut, scene.gt_labels))


def frames(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> LazyFrames:
    """The frames of :func:`load`'s scene without sampling the cloud (a tiled run's worker):
    rendered when read from the blocks around each camera."""
    city = City(cfg.options, sensor)
    return _frames_in(LazyFrames([v[0] for v in city.views], city.frame, poses=[v[3] for v in city.views]),
                      _lut(taxonomy))
