"""analysis.gains: ground-truth boundary pixels split into creases and coplanar boundaries."""
import numpy as np

from analysis.gains import KINDS, pixel_kinds
from diffuser_lab.data.render import MeshRenderer, intrinsics, look_at


def _corner():
    """A floor (z = 0, class 1) meeting a wall (y = 1) whose left half is class 0, right half 2."""
    v = np.array([[-2, -1, 0], [2, -1, 0], [2, 1, 0], [-2, 1, 0],  # floor
                  [-2, 1, 0], [0, 1, 0], [0, 1, 2], [-2, 1, 2],  # wall, left
                  [0, 1, 0], [2, 1, 0], [2, 1, 2], [0, 1, 2]], np.float64)  # wall, right
    t = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [8, 9, 10], [8, 10, 11]], np.int32)
    return MeshRenderer(v, t, np.array([1, 1, 0, 0, 2, 2], np.int16))


def test_crease_at_the_floor_wall_junction_coplanar_at_the_wall_split():
    W, H = 160, 120
    K = intrinsics(W, H, 70.0)
    depth, gt = _corner().render(K, look_at((0.3, -1.5, 1.2), (0.0, 1.0, 0.5)), W, H)
    kinds = pixel_kinds(gt, depth, K)
    crease, coplanar = KINDS.index("crease"), KINDS.index("coplanar")
    floor_wall = (gt == 1) & np.roll(gt != 1, 2, axis=0)  # floor pixels just below a wall pixel
    split = ((gt == 0) & np.roll(gt == 2, -2, axis=1)) | ((gt == 2) & np.roll(gt == 0, 2, axis=1))
    assert floor_wall.sum() > 20 and split.sum() > 20
    assert np.mean(kinds[floor_wall] == crease) > 0.8
    assert np.mean(kinds[split & ~np.roll(gt == 1, -3, axis=0)] == coplanar) > 0.8
    assert np.mean(kinds[(gt == 0)] == KINDS.index("interior")) > 0.5
