"""protocol.normals=depth_image: a target frame's normals from its organised depth image."""
import numpy as np

from diffuser_lab.data.geometry import backproject
from diffuser_lab.data.render import intrinsics, look_at
from diffuser_lab.data.scene import Frame
from diffuser_lab.runs.single_frame import image_normals


def test_normals_of_a_noisy_tilted_plane_face_the_camera():
    H, W = 120, 160
    K = intrinsics(W, H, 60.0)
    T_cw = look_at((0.0, -2.0, 1.0), (0.0, 0.0, 0.0))
    # the plane z = 0 seen from the camera: depth by ray casting, plus 5 mm of noise
    R_wc, c = np.linalg.inv(T_cw)[:3, :3], np.linalg.inv(T_cw)[:3, 3]
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ R_wc.T  # world directions, z_cam = 1
    t = -c[2] / rays[..., 2]
    depth = np.where(t > 0, t, 0.0) + np.random.default_rng(0).normal(0, 0.005, (H, W)) * (t > 0)
    f = Frame(name="plane", K=K, T_cw=T_cw, depth=depth.astype(np.float32), labels=np.zeros((H, W), np.int16))
    pts, pix = backproject(f.depth, K, T_cw)
    n = image_normals(f, pix, np.arange(len(pts)), len(pts), 7)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    inner = (pix[:, 0] > 5) & (pix[:, 0] < H - 5) & (pix[:, 1] > 5) & (pix[:, 1] < W - 5)
    assert np.median(n[inner] @ np.array([0.0, 0.0, 1.0])) > 0.99  # the plane's normal, towards the camera
    raw = image_normals(f, pix, np.arange(len(pts)), len(pts), 1)
    assert np.median(raw[inner] @ np.array([0.0, 0.0, 1.0])) < np.median(n[inner] @ np.array([0.0, 0.0, 1.0]))
