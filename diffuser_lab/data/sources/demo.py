"""Procedural demo room: a labelled box-mesh scene with exact depth and label views.

The room occupies ``[0, Lx] x [0, Ly] x [0, Lz]`` (metres, z up). Its shell is a
floor and four walls made of one-sided quads facing the inside (no ceiling, like
most ScanNet reconstructions); furniture and wall items are closed, outward-wound
boxes. Furniture stands ``_LIFT`` above the floor and wall items hang ``_GAP`` off
the walls so that :func:`~diffuser_lab.data.render.sample_surface` recognises the
covered surfaces (floor under a cabinet, wall behind a picture) and drops them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from diffuser_lab import seeding
from diffuser_lab.config import SceneConfig, Section, at_least, check, key, rule, within
from diffuser_lab.data.mapping import relabel_scene
from diffuser_lab.data.render import MeshRenderer, camera_trajectory, intrinsics, render_views, sample_surface
from diffuser_lab.data.scene import SCANNET20, Frame, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel

__all__ = ["DemoOptions", "make_demo_scene", "demo_mesh", "load"]


@dataclass
class DemoOptions(Section):
    """Procedural room (diffuser_lab.data.sources.demo)."""

    KEY = "scene.options"
    seed: int = 0
    room_size: List[float] = key(check=rule("three sizes > 1 m", lambda v: len(v) == 3 and min(v) > 1.0),
                                 factory=lambda: [5.0, 4.0, 2.6])  # x, y, z metres
    n_views: int = key(30, at_least(1))
    image_width: int = 160
    image_height: int = 120
    fov_deg: float = key(70.0, within(10, 150))  # horizontal field of view
    point_spacing: float = key(0.04, within(0.005, 0.5, "metres"))  # metres between sampled surface points
    point_noise: float = key(0.002, at_least(0))  # std of gaussian position noise, metres

    def _check_keys(self) -> None:
        check(self.image_width >= 16 and self.image_height >= 16, "scene.options.image_width/height",
               (self.image_width, self.image_height), ">= 16 pixels")


_LIFT = 0.005  # m, furniture bottom above the floor plane
_GAP = 0.005  # m, wall items / furniture backs off the wall plane
_C = {n: i for i, n in enumerate(SCANNET20.names)}

# Corner sign patterns (bit 0 = x, bit 1 = y, bit 2 = z) and the 12 triangles of a box;
# winding is fixed up to outward afterwards, so only the face grouping matters here.
_SIGNS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64) - 0.5
_BOX_TRIS = np.array([
    [0, 2, 1], [1, 2, 3],  # z-
    [4, 5, 6], [5, 7, 6],  # z+
    [0, 1, 4], [1, 5, 4],  # y-
    [2, 6, 3], [3, 6, 7],  # y+
    [0, 4, 2], [2, 4, 6],  # x-
    [1, 3, 5], [3, 7, 5],  # x+
])


class _Builder:
    """Accumulates boxes (object-local specs) and shell quads into one mesh."""

    def __init__(self):
        self.boxes: list[tuple[np.ndarray, np.ndarray, float, int]] = []  # centre, size, yaw, label
        self.quads: list[tuple[np.ndarray, np.ndarray, int]] = []  # (4,3) corners, normal, label

    def add_object(self, parts, pos, yaw, z0=_LIFT):
        """parts: list of (local centre (3,), size (3,), label) with z measured from the
        object's base; placed at floor position ``pos`` (2,), rotated by ``yaw`` (rad)."""
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        off = np.array([pos[0], pos[1], z0])
        for centre, size, label in parts:  # loop over a handful of parts
            self.boxes.append((R @ np.asarray(centre, float) + off, np.asarray(size, float), yaw, label))

    def mesh(self):
        verts, tris, labs = [], [], []
        nv = 0
        for centre, size, yaw, label in self.boxes:
            c, s = np.cos(yaw), np.sin(yaw)
            R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            v = centre + (_SIGNS * size) @ R.T
            t = _BOX_TRIS.copy()
            # Orient every triangle outward (normal away from the box centre).
            n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
            flip = np.einsum("tk,tk->t", n, v[t].mean(1) - centre) < 0
            t[flip] = t[flip][:, ::-1]
            verts.append(v)
            tris.append(t + nv)
            labs.append(np.full(12, label))
            nv += 8
        for corners, normal, label in self.quads:
            t = np.array([[0, 1, 2], [0, 2, 3]])
            n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
            if n @ normal < 0:
                t = t[:, ::-1]
            verts.append(corners)
            tris.append(t + nv)
            labs.append(np.full(2, label))
            nv += 4
        return (np.concatenate(verts).astype(np.float32), np.concatenate(tris).astype(np.int32),
                np.concatenate(labs).astype(np.int16))


# ---------------------------------------------------------------- furniture parts
# Object-local frame: x along the width, +y = front (away from the wall it backs onto),
# z up from the object's base; footprint centred on the origin.

def _legs(w, d, h, t, inset):
    xs, ys = w / 2 - inset - t / 2, d / 2 - inset - t / 2
    return [((sx * xs, sy * ys, h / 2), (t, t, h)) for sx in (-1, 1) for sy in (-1, 1)]


def _table(rng, label=_C["table"], w=None, d=None):
    w = rng.uniform(1.2, 1.6) if w is None else w
    d = rng.uniform(0.7, 0.9) if d is None else d
    h, th = rng.uniform(0.72, 0.78), 0.04
    parts = [((0, 0, h - th / 2), (w, d, th), label)]
    parts += [(c, s, label) for c, s in _legs(w, d, h - th, 0.05, 0.05)]
    return parts, (w, d), h


def _chair(rng):
    w = d = rng.uniform(0.42, 0.5)
    hs, th, hb = rng.uniform(0.43, 0.48), 0.04, rng.uniform(0.4, 0.5)
    L = _C["chair"]
    parts = [((0, 0, hs - th / 2), (w, d, th), L)]
    parts += [(c, s, L) for c, s in _legs(w, d, hs - th, 0.04, 0.02)]
    parts.append(((0, -d / 2 + 0.02, hs + hb / 2), (w, 0.04, hb), L))  # back at local -y
    return parts, (w, d), hs + hb


def _desk(rng):
    w, d, h, th = rng.uniform(1.0, 1.4), rng.uniform(0.55, 0.7), rng.uniform(0.72, 0.76), 0.03
    L = _C["desk"]
    parts = [((0, 0, h - th / 2), (w, d, th), L),
             ((-w / 2 + 0.02, 0, (h - th) / 2), (0.04, d, h - th), L),  # side panels
             ((w / 2 - 0.02, 0, (h - th) / 2), (0.04, d, h - th), L),
             ((0, -d / 2 + 0.02, (h - th) / 2 + 0.2), (w - 0.08, 0.02, h - th - 0.4), L)]  # modesty panel
    return parts, (w, d), h


def _cabinet(rng):
    w, d, h = rng.uniform(0.8, 1.2), rng.uniform(0.45, 0.6), rng.uniform(0.8, 1.1)
    L = _C["cabinet"]
    parts = [((0, 0, h / 2), (w, d, h), L)]
    n_door = 2 if w > 1.0 else 1
    dw = (w - 0.04) / n_door
    for k in range(n_door):  # door fronts protrude 1.5 cm
        x = -w / 2 + 0.02 + dw * (k + 0.5)
        parts.append(((x, d / 2 + 0.0075, h / 2), (dw - 0.01, 0.015, h - 0.06), L))
    return parts, (w, d + 0.015), h


def _bookshelf(rng):
    w, d, h, t = rng.uniform(0.8, 1.0), rng.uniform(0.3, 0.36), rng.uniform(1.6, 2.0), 0.03
    L = _C["bookshelf"]
    parts = [((-w / 2 + t / 2, 0, h / 2), (t, d, h), L), ((w / 2 - t / 2, 0, h / 2), (t, d, h), L),
             ((0, -d / 2 + 0.01, h / 2), (w - 2 * t, 0.02, h), L)]  # back panel
    n_shelf = int(rng.integers(4, 6))
    for z in np.linspace(t / 2, h - t / 2, n_shelf):
        parts.append(((0, 0.01, z), (w - 2 * t, d - 0.02, t), L))
    return parts, (w, d), h


def _sofa(rng):
    w, d = rng.uniform(1.8, 2.2), rng.uniform(0.85, 0.95)
    hs, hb, ha, arm = rng.uniform(0.40, 0.45), rng.uniform(0.75, 0.85), rng.uniform(0.55, 0.65), 0.2
    L = _C["sofa"]
    parts = [((0, 0.1, hs / 2), (w - 2 * arm, d - 0.2, hs), L),  # seat block
             ((0, -d / 2 + 0.1, hb / 2), (w - 2 * arm, 0.2, hb), L),  # back
             ((-w / 2 + arm / 2, 0, ha / 2), (arm, d, ha), L),  # arms
             ((w / 2 - arm / 2, 0, ha / 2), (arm, d, ha), L)]
    return parts, (w, d), hb


def _bed(rng):
    w, d = rng.uniform(1.4, 1.6), rng.uniform(1.95, 2.05)
    hm, hh = rng.uniform(0.45, 0.55), rng.uniform(0.9, 1.1)
    L = _C["bed"]
    parts = [((0, 0.04, hm / 2), (w, d - 0.08, hm), L),
             ((0, -d / 2 + 0.04, hh / 2), (w + 0.06, 0.08, hh), L)]  # headboard against the wall
    return parts, (w, d), hh


def _side_table(rng):
    w, h = rng.uniform(0.35, 0.5), rng.uniform(0.45, 0.6)
    return [((0, 0, h / 2), (w, w, h), _C["otherfurniture"])], (w, w), h


# ---------------------------------------------------------------- placement

class _Floor:
    """Occupied floor rectangles with the height allowed to overlap each
    (0 = nothing may stand there; a window's sill height lets low furniture under it)."""

    def __init__(self, L):
        self.L = L
        self.rects: list[tuple[np.ndarray, np.ndarray, float]] = []

    def free(self, lo, hi, height, clearance=0.1):
        if np.any(lo < -1e-9) or np.any(hi > self.L[:2] + 1e-9):
            return False
        for rlo, rhi, allowed in self.rects:  # loop over placed objects
            if height > allowed and np.all(lo < rhi + clearance) and np.all(rlo < hi + clearance):
                return False
        return True

    def add(self, lo, hi, allowed=0.0):
        self.rects.append((np.asarray(lo, float), np.asarray(hi, float), allowed))


def _wall_frame(L, k):
    """Wall k: (origin (2,), along (2,), inward normal (2,), length) in the floor plane."""
    Lx, Ly = L[0], L[1]
    return [(np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), Lx),
            (np.array([Lx, 0.0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), Ly),
            (np.array([Lx, Ly]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), Lx),
            (np.array([0.0, Ly]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), Ly)][k]


def _footprint(pos, yaw, wd):
    """Axis-aligned floor rectangle (lo, hi) of a (w, d) footprint at pos rotated by yaw."""
    c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
    half = 0.5 * np.array([c * wd[0] + s * wd[1], s * wd[0] + c * wd[1]])
    return pos - half, pos + half


def _place_against_wall(b, floor, rng, make, front_reserve=0.0, tries=40):
    """Put an object with its back to a random wall where the floor is free; the
    checked/reserved rectangle extends ``front_reserve`` metres in front of it.
    Returns (pos (2,), yaw, (w, d)) or None."""
    parts, wd, h = make(rng)
    for _ in range(tries):
        o, a, n, length = _wall_frame(floor.L, int(rng.integers(4)))
        if length < wd[0] + 0.1:
            continue
        s = rng.uniform(wd[0] / 2 + 0.05, length - wd[0] / 2 - 0.05)
        pos = o + s * a + n * (wd[1] / 2 + _GAP + rng.uniform(0.0, 0.02))
        yaw = np.arctan2(-n[0], n[1])  # local +y (front) -> inward normal
        lo, hi = _footprint(pos + n * front_reserve / 2, yaw, (wd[0], wd[1] + front_reserve))
        if floor.free(lo, hi, h):
            b.add_object(parts, pos, yaw)
            floor.add(lo, hi)
            return pos, yaw, wd
    return None


def _wall_item(b, floor, rng, label, width, height, z_bottom, thick, reserve_depth, allowed,
               reserve_width=None, tries=40):
    """Thin box hung ``_GAP`` off a random wall, not overlapping other wall items;
    reserves a floor strip (``reserve_width`` x ``reserve_depth`` metres) in front of
    it for objects taller than ``allowed`` metres. Returns (pos (2,), yaw) or None."""
    rw = width if reserve_width is None else reserve_width
    for _ in range(tries):
        o, a, n, length = _wall_frame(floor.L, int(rng.integers(4)))
        if length < rw + 0.4:
            continue
        s = rng.uniform(rw / 2 + 0.2, length - rw / 2 - 0.2)
        pos = o + s * a + n * (_GAP + thick / 2)
        yaw = np.arctan2(-n[0], n[1])
        lo, hi = _footprint(o + s * a + n * (reserve_depth / 2), yaw, (rw, reserve_depth))
        if not floor.free(lo, hi, np.inf, clearance=0.05):
            continue
        b.add_object([((0, 0, height / 2), (width, thick, height), label)], pos, yaw, z0=z_bottom)
        floor.add(lo, hi, allowed)
        return pos, yaw
    return None


def demo_mesh(seed: int = 0, room_size=(5.0, 4.0, 2.6)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labelled triangle mesh of the procedural demo room.

    Args:
        seed: placement/size randomness (deterministic per seed).
        room_size: (Lx, Ly, Lz) metres; the room spans [0, L] on each axis, z up.

    Returns:
        vertices (V, 3) float32 metres, triangles (T, 3) int32 with outward winding
        (shell quads face the room), triangle_labels (T,) int16 SCANNET20 ids.
    """
    # the layout's own stream, the seed alone (the room every figure so far shows): nothing else
    # draws from it, and its draws depend on the layout's own decisions only
    rng = seeding.keyed("demo.layout", seed)
    L = np.asarray(room_size, np.float64)
    b = _Builder()

    # Shell: floor and four walls facing inward.
    Lx, Ly, Lz = L
    b.quads.append((np.array([[0, 0, 0], [Lx, 0, 0], [Lx, Ly, 0], [0, Ly, 0]], float),
                    np.array([0, 0, 1.0]), _C["floor"]))
    for k in range(4):
        o, a, n, length = _wall_frame(L, k)
        p0, p1 = o, o + length * a
        b.quads.append((np.array([[*p0, 0], [*p1, 0], [*p1, Lz], [*p0, Lz]], float),
                        np.array([n[0], n[1], 0.0]), _C["wall"]))

    # Layouts are rejection-sampled: retry the whole furnishing (the layout's own stream,
    # decided by the layout alone) when a required piece does not fit.
    shell = list(b.quads)
    for _ in range(50):
        b.boxes, b.quads = [], list(shell)
        if _furnish(b, _Floor(L), rng):
            return b.mesh()
    raise RuntimeError(f"demo_mesh: could not furnish a room of size {tuple(L)} (too small?)")


class _NoFit(Exception):
    pass


def _furnish(b: _Builder, floor: _Floor, rng: np.random.Generator) -> bool:
    """Add wall items and furniture; False when a required piece did not fit."""
    try:
        _furnish_or_raise(b, floor, rng)
    except _NoFit:
        return False
    return True


def _need(x):
    if x is None:
        raise _NoFit
    return x


def _furnish_or_raise(b: _Builder, floor: _Floor, rng: np.random.Generator) -> None:
    L = floor.L
    Lz = L[2]
    # Wall items first so that doors stay reachable and pictures stay visible.
    dw, dh = rng.uniform(0.85, 0.95), min(rng.uniform(2.0, 2.1), Lz - 0.1)
    _need(_wall_item(b, floor, rng, _C["door"], dw, dh, _LIFT, 0.04, 1.0, 0.0))
    ww, wh, sill = rng.uniform(1.0, 1.5), rng.uniform(1.0, 1.3), rng.uniform(0.8, 1.0)
    curtains = rng.random() < 0.5
    cw = 0.3  # curtain width, m; one on each side of the window
    wpos, wyaw = _need(_wall_item(b, floor, rng, _C["window"], ww, min(wh, Lz - sill - 0.2), sill,
                                  0.03, 0.6, sill - 0.05,
                                  reserve_width=ww + 2 * (cw + 0.05) if curtains else None))
    if curtains:
        along = np.array([np.cos(wyaw), np.sin(wyaw)])
        inward = np.array([-np.sin(wyaw), np.cos(wyaw)])
        ch = Lz - 0.3
        for side in (-1, 1):  # hung 6 cm in front of the wall, standing on the floor
            pos = wpos + along * side * (ww / 2 + 0.03 + cw / 2) + inward * 0.06
            b.add_object([((0, 0, ch / 2), (cw, 0.06, ch), _C["curtain"])], pos, wyaw)
            floor.add(*_footprint(pos, wyaw, (cw, 0.5)))
    pw, ph = rng.uniform(0.4, 0.8), rng.uniform(0.3, 0.6)
    pz = rng.uniform(1.35, 1.6) - ph / 2
    _need(_wall_item(b, floor, rng, _C["picture"], pw, ph, pz, 0.02, 0.6, pz - 0.05))

    # Wall-backed furniture, biggest first: sofa (or sometimes a bed), bookshelf, cabinet.
    big = _bed if rng.random() < 0.3 else _sofa
    for make in (big, _bookshelf, _cabinet):
        _need(_place_against_wall(b, floor, rng, make, front_reserve=0.2))

    # Table with chairs around it wherever the floor is free.
    t_parts, (tw, td), th = _table(rng)
    n_chairs = int(rng.integers(2, 5))
    seats = [(0.0, -1.0), (0.0, 1.0), (-1.0, 0.0), (1.0, 0.0)][:n_chairs]  # sides of the table
    for _ in range(60):
        yaw = float(rng.choice([0.0, np.pi / 2])) + rng.uniform(-0.1, 0.1)
        pos = rng.uniform([0.5, 0.5], L[:2] - 0.5)
        lo, hi = _footprint(pos, yaw, (tw + 1.0, td + 1.0))  # table + chair ring
        if floor.free(lo, hi, th):
            break
    else:
        raise _NoFit
    b.add_object(t_parts, pos, yaw)
    floor.add(lo, hi)
    c, s = np.cos(yaw), np.sin(yaw)
    R2 = np.array([[c, -s], [s, c]])
    for sx, sy in seats:  # chairs face the table, backs away from it
        local = np.array([sx * (tw / 2 + 0.12), sy * (td / 2 + 0.12)])
        cpos = pos + R2 @ local + rng.uniform(-0.05, 0.05, 2)
        cyaw = yaw + np.arctan2(sx, -sy) + rng.uniform(-0.25, 0.25)
        b.add_object(_chair(rng)[0], cpos, cyaw)

    # Optional pieces: a desk with its chair, a side table.
    placed = _place_against_wall(b, floor, rng, _desk, front_reserve=0.6)
    if placed is not None:  # chair pulled up to the desk, in the reserved strip
        dpos, dyaw, (_, ddep) = placed
        front = np.array([-np.sin(dyaw), np.cos(dyaw)])
        cpos = dpos + front * (ddep / 2 + 0.12) + rng.uniform(-0.05, 0.05, 2)
        b.add_object(_chair(rng)[0], cpos, dyaw + np.pi + rng.uniform(-0.3, 0.3))
    _place_against_wall(b, floor, rng, _side_table, front_reserve=0.1)


def make_demo_scene(
    *,
    seed: int = 0,
    room_size=(5.0, 4.0, 2.6),
    n_views: int = 30,
    image_width: int = 160,
    image_height: int = 120,
    fov_deg: float = 70.0,
    point_spacing: float = 0.04,
    point_noise: float = 0.002,
    sensor=None,
) -> tuple[Scene, MeshRenderer]:
    """Procedural labelled room with a point cloud and rendered ground-truth views.

    Args:
        seed: makes mesh, points and cameras deterministic: the layout, each triangle's samples
            and each camera candidate draw from their own keyed streams (:mod:`diffuser_lab.seeding`).
        room_size: (Lx, Ly, Lz) room extent, metres.
        n_views: number of frames along a handheld-like camera path.
        image_width, image_height: frame size, pixels. fov_deg: horizontal FOV, degrees.
        point_spacing: metres, one sampled point per ``point_spacing^2`` of visible area.
        point_noise: std of gaussian point position noise, metres.
        sensor: a :class:`~diffuser_lab.data.sensor.SensorModel` for the frames' depth, or None
            (perfect z-depth). The points, poses and label images do not depend on it.

    Returns:
        scene: points (N, 3) float32, normals (N, 3) float32 (exact mesh normals),
            gt_labels (N,) int16, SCANNET20 taxonomy, frames with K, T_cw, depth
            (z-depth, metres, 0 = no hit), ``labels=None`` and ``gt_labels`` (label image).
        renderer: :class:`MeshRenderer` of the room mesh (for more views).
    """
    verts, tris, tri_labels = demo_mesh(seed, room_size)
    renderer = MeshRenderer(verts, tris, tri_labels)
    points, normals, labels = sample_surface(verts, tris, tri_labels, point_spacing, seed,
                                             noise=point_noise, renderer=renderer)
    K = intrinsics(image_width, image_height, fov_deg)
    poses = camera_trajectory(verts, n_views, seed, width=image_width, height=image_height,
                              K=K, renderer=renderer)
    views = render_views(renderer, K, poses, image_width, image_height, sensor=sensor)
    frames = [Frame(name=f"view_{i:04d}", K=K.copy(), T_cw=T, depth=depth, labels=None, gt_labels=lab)
              for i, (T, (depth, lab)) in enumerate(zip(poses, views))]
    scene = Scene(name=f"demo_room_seed{seed}", points=points, taxonomy=SCANNET20,
                  frames=frames, normals=normals, gt_labels=labels)
    return scene, renderer


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=demo``: the room of the ``scene.options`` keys, relabelled to ``taxonomy``."""
    d = cfg.options
    scene, _ = make_demo_scene(seed=d.seed, room_size=tuple(d.room_size), n_views=d.n_views,
                               image_width=d.image_width, image_height=d.image_height,
                               fov_deg=d.fov_deg, point_spacing=d.point_spacing, point_noise=d.point_noise,
                               sensor=sensor)
    if taxonomy.name != scene.taxonomy.name:
        scene = relabel_scene(scene, taxonomy)
    return scene
