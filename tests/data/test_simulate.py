"""Simulated 2D network mistakes (diffuser_lab.data.simulate)."""
import numpy as np
import pytest
from scipy import ndimage

from diffuser_lab.data.scene import IGNORE, SCANNET20
from diffuser_lab.data.simulate import simulate_predictions
from diffuser_lab.data.sources.demo import make_demo_scene

C = SCANNET20.num_classes
N = SCANNET20.names.index


def _miou_2d(pred, gt, num_classes):
    """Percent mIoU over the classes present in gt; IGNORE gt pixels excluded."""
    v = gt != IGNORE
    cm = np.bincount(gt[v].astype(np.int64) * num_classes + pred[v].astype(np.int64),
                     minlength=num_classes**2).reshape(num_classes, num_classes)
    tp = np.diag(cm)
    present = cm.sum(1) > 0
    return 100.0 * (tp[present] / (cm.sum(0) + cm.sum(1) - tp)[present]).mean()


@pytest.fixture(scope="module")
def views():
    scene, _ = make_demo_scene(seed=0)
    return [f.gt_labels for f in scene.frames]


def _mean_miou(views, seed, **kw):
    return np.mean([_miou_2d(simulate_predictions(g, C, (seed, i), **kw), g, C) for i, g in enumerate(views)])


def test_strength_zero_is_identity(views):
    for g in views[:5]:
        p = simulate_predictions(g, C, 0, strength=0.0)
        assert p.dtype == np.int16 and np.array_equal(p, g)


def test_default_miou_in_calibrated_range(views):
    m = _mean_miou(views, 0)
    assert 50.0 <= m <= 65.0, m
    # Strength scales the damage monotonically.
    assert _mean_miou(views, 0, strength=0.5) > m + 5 > _mean_miou(views, 0, strength=2.0) + 10


def test_ignore_stays_ignore_and_valid_stays_valid(views):
    for i, g in enumerate(views):
        g = g.copy()
        g[40:60, :30] = IGNORE  # a depth hole inside the image as well
        p = simulate_predictions(g, C, (1, i), strength=2.0)
        assert (p[g == IGNORE] == IGNORE).all()
        assert ((p[g != IGNORE] >= 0) & (p[g != IGNORE] < C)).all()
    allign = np.full((12, 16), IGNORE, np.int16)
    assert (simulate_predictions(allign, C, 1) == IGNORE).all()


def test_deterministic_and_independent_per_key(views):
    g = views[3]
    a = simulate_predictions(g, C, (7, 3))
    b = simulate_predictions(g, C, (7, 3))
    assert np.array_equal(a, b)
    c, d = simulate_predictions(g, C, (7, 4)), simulate_predictions(g, C, (8, 3))
    assert not np.array_equal(a, c) and not np.array_equal(a, d)
    with pytest.raises(TypeError, match="expected an int or a sequence of ints"):
        simulate_predictions(g, C, np.random.default_rng(7))


def test_one_more_region_changes_no_other_draw(views):
    """Draws are keyed by what they are for (a region by its class and first pixel, the blobs and
    the warp by the view): a small new region in a corner changes the labels near it only, not the
    rest of the view (a shared generator's running state would shift every later draw)."""
    for i, g in enumerate(views[:8]):
        h = g.copy()
        h[-6:, -6:] = N("toilet")  # a class the room does not have, in the bottom-right corner
        a, b = simulate_predictions(g, C, (5, i)), simulate_predictions(h, C, (5, i))
        far = np.ones(g.shape, bool)
        far[-6 - 16:, -6 - 16:] = False  # the new region and the warp's reach (3 px x 4 sigma) around it
        assert np.array_equal(a[far], b[far]), i


def test_errors_are_coherent_not_salt_noise(views):
    isolated = wrong = 0
    for i, g in enumerate(views):
        p = simulate_predictions(g, C, (2, i))
        err = (p != g) & (g != IGNORE)
        # A wrong pixel whose 4 neighbours are all right is salt noise.
        n_err_nb = ndimage.convolve(err.astype(int), np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]]),
                                    mode="constant")
        isolated += np.count_nonzero(err & (n_err_nb == 0))
        wrong += np.count_nonzero(err)
    assert wrong > 0 and isolated / wrong < 0.02


def test_boundary_jitter_only_changes_pixels_near_boundaries(views):
    for i, g in enumerate(views[:10]):
        p = simulate_predictions(g, C, (3, i), confuse_prob=0.0, blob_count=0.0, jitter_px=3.0)
        changed = p != g
        boundary = np.zeros_like(changed)
        boundary[:, 1:] |= g[:, 1:] != g[:, :-1]
        boundary[1:, :] |= g[1:, :] != g[:-1, :]
        dist = ndimage.distance_transform_edt(~boundary)
        assert (dist[changed] <= 4 * 3.0).all()


def test_region_confusion_uses_plausible_classes():
    g = np.full((60, 80), N("wall"), np.int16)
    g[30:, :] = N("floor")
    g[20:45, 10:25] = N("chair")
    g[25:50, 40:70] = N("table")
    for seed in range(10):
        p = simulate_predictions(g, C, seed, confuse_prob=1.0, confuse_max_frac=1.0,
                                 blob_count=0.0, jitter_px=0.0)
        chair, table = p[20:45, 10:25], p[25:50, 40:70]
        # Whole regions switch class together, to a plausible confusion.
        assert len(np.unique(chair)) == 1 and len(np.unique(table)) == 1
        assert chair[0, 0] in {N("sofa"), N("otherfurniture"), N("table")}
        assert table[0, 0] in {N("desk"), N("counter"), N("otherfurniture")}
    # Regions larger than confuse_max_frac are kept.
    p = simulate_predictions(g, C, 0, confuse_prob=1.0, confuse_max_frac=0.2,
                             blob_count=0.0, jitter_px=0.0)
    assert (p[g == N("wall")] == N("wall")).all() and (p[g == N("floor")] == N("floor")).all()


def test_blobs_are_compact_regions():
    g = np.full((120, 160), N("wall"), np.int16)
    p = simulate_predictions(g, C, 4, confuse_prob=0.0, jitter_px=0.0,
                             blob_count=3.0)
    err = p != g
    _, n = ndimage.label(err)
    assert 0 < err.mean() < 0.4 and n <= 12
    # Without a confusion table the wrong class is some other class.
    p = simulate_predictions(g, 5, 4, confuse_prob=0.0, jitter_px=0.0,
                             blob_count=3.0)
    assert set(np.unique(p)) <= set(range(5)) and (p != g).any()
