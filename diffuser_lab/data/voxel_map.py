"""A growing point map for the online protocol: each frame's back-projected points merged on a
fixed world voxel grid, one point per occupied voxel, a point never moving once made
(:class:`VoxelMap`). Its index of occupied voxels is a compiled hash table or numpy's sorted keys
(:func:`diffuser_lab.backends.voxel_map.voxel_index`, decided when a map is made; same results).
"""
from __future__ import annotations

import numpy as np

from diffuser_lab.backends.voxel_map import voxel_index


def _unit(nsum: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Normalised rows of the (m, 3) float64 sums; a zero sum takes the row of ``fallback``."""
    norm = np.sqrt(np.einsum("ij,ij->i", nsum, nsum))
    out = nsum / np.where(norm > 0, norm, 1.0)[:, None]
    bad = ~(norm > 0)
    out[bad] = fallback[bad]
    return out.astype(np.float32)


class VoxelMap:
    """Points merged on a voxel grid of ``voxel_size`` metres (world frame, grid anchored at the
    world origin so it never moves as the map grows): one point per occupied voxel.

    Attributes:
        n: occupied voxels so far. voxel_size: metres.
    """

    def __init__(self, voxel_size: float):
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self.n = 0
        self._index = voxel_index(self.voxel_size)
        self._nb = self._index.compiled

    def occupied(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool: the point's voxel already holds a map point (:meth:`insert` would drop it)."""
        points = np.ascontiguousarray(points, np.float32)
        if self.n == 0 or points.shape[0] == 0:
            return np.zeros(points.shape[0], bool)
        return self._index.occupied(points)

    def insert(self, points: np.ndarray, normals: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """Merge one frame.

        Args:
            points: (M, 3) float32 world points, metres; normals: (M, 3) unit normals or None.
        Returns:
            the NEW map points (m, 3) float32 and their normals (m, 3) float32 or None, in Morton
            order of their voxel keys. Points in voxels occupied by earlier frames are dropped (the
            map point there stays); the points of this frame in one new voxel become their centroid
            (float64 sums) and the normalised sum of their normals (the first point's normal if that
            sum is 0).
        """
        points = np.ascontiguousarray(points, np.float32)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must be (M, 3), got {points.shape}")
        if normals is not None:
            normals = np.ascontiguousarray(normals, np.float32)
            if normals.shape != points.shape:
                raise ValueError(f"normals must be (M, 3) like the points, got {normals.shape}")
        sums, nsums, counts, first = self._index.insert(points, normals, self.n)
        self.n += counts.shape[0]
        pts = (sums / counts[:, None]).astype(np.float32)
        nrm = _unit(nsums, normals[first]) if normals is not None else None
        return pts, nrm
