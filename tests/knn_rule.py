"""The rule of every kNN row (diffuser_lab/backends/knn.py), written out by brute force for the
tests of the batch graph (tests/backends/test_knn.py) and the growing one (tests/method/test_growing.py)."""
import numpy as np


def brute_rows(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, K) int64 every row of the (N, 3) points: d2 = ((dx*dx + dy*dy) + dz*dz) in float64 from
    the coordinates, self excluded, the K smallest by (d2, index) in that order; and their (N, K) d2."""
    p = points.astype(np.float64)
    dx, dy, dz = (p[None, :, a] - p[:, None, a] for a in range(3))
    d = (dx * dx + dy * dy) + dz * dz
    np.fill_diagonal(d, np.inf)
    o = np.lexsort((np.broadcast_to(np.arange(len(p)), d.shape), d), axis=-1)[:, :k]
    return o, np.take_along_axis(d, o, 1)
