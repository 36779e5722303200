"""diffuser_lab/data/poses.py: the one trajectory rule (interpolate_poses) every source uses."""
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from diffuser_lab.data.poses import interpolate_poses, rigid_inverse


def test_interpolated_pose_is_the_slerp_midpoint():
    st = np.array([0, 100_000_000], np.int64)  # nanoseconds
    q = Rotation.from_euler("z", [[0], [90]], degrees=True).as_quat()
    T, ok = interpolate_poses(st, np.array([[0, 0, 0], [1, 0, 0.0]]), q, np.array([25_000_000, 300_000_000]), 0.08e9)
    assert ok.tolist() == [True, False]
    np.testing.assert_allclose(T[0, :3, 3], [0.25, 0, 0])
    np.testing.assert_allclose(Rotation.from_matrix(T[0, :3, :3]).as_euler("zyx", degrees=True)[0], 22.5)
    T, _ = interpolate_poses(st, np.array([[0, 0, 0], [1, 0, 0.0]]), q, np.array([25_000_000]), 0.08e9, False)
    np.testing.assert_allclose(T[0, :3, 3], 0)  # the nearest sample


def test_interpolation_agrees_with_scipy_slerp_and_falls_back_to_the_nearest():
    rng = np.random.default_rng(0)
    st = np.sort(rng.uniform(0, 1, 40)) + 1.3e9  # seconds, epoch-sized
    rots = Rotation.random(40, random_state=1)
    tr = rng.normal(size=(40, 3))
    inside = np.sort(rng.uniform(st[0], st[-1], 200))
    T, ok = interpolate_poses(st, tr, rots.as_quat(), inside, 1.0)
    assert ok.all()
    ref = Slerp(st, rots)(inside).as_matrix()
    np.testing.assert_allclose(T[:, :3, :3], ref, atol=1e-9)
    lin = np.stack([np.interp(inside, st, tr[:, k]) for k in range(3)], 1)
    np.testing.assert_allclose(T[:, :3, 3], lin, atol=1e-9)
    # a gap wider than the tolerance: the nearest sample within it, none beyond it
    at = np.array([st[0] - 0.001, st[-1] + 0.5])
    T, ok = interpolate_poses(st, tr, rots.as_quat(), at, 0.01)
    assert ok.tolist() == [True, False]
    np.testing.assert_allclose(T[0, :3, 3], tr[0])
    # rigid_inverse of a stack equals each one's
    np.testing.assert_allclose(rigid_inverse(T)[0] @ T[0], np.eye(4), atol=1e-12)
