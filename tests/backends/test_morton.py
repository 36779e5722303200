"""Morton order (diffuser_lab.backends.morton, its compiled twin backends/numba/morton.py): a stable
sort of the codes on both paths, so points with equal codes (duplicates, points within one lattice
step) keep their input order on any CPU (numpy >= 2 sorts with AVX-512 simd-sort by default, whose
order among equal keys is its own)."""
import numpy as np
import pytest

from diffuser_lab.backends import numba as nb
from diffuser_lab.backends.morton import morton_codes, quantize, spatial_order


def tied_cloud(seed=0):
    """3000 points, each of 100 positions repeated 30 times, shuffled: every code ties 30 ways."""
    rng = np.random.default_rng(seed)
    base = rng.random((100, 3)).astype(np.float32)
    return base[rng.permutation(np.repeat(np.arange(100), 30))]


def assert_stable(order, codes):
    """order sorts codes, and indices with equal codes come in ascending order."""
    c = codes[order]
    assert np.all(c[1:] >= c[:-1])
    tie = c[1:] == c[:-1]
    assert tie.sum() == len(c) - 100 and np.all(order[1:][tie] > order[:-1][tie])


def test_spatial_order_is_stable():
    pts = tied_cloud()
    codes = morton_codes(quantize(pts)[0])
    assert_stable(spatial_order(pts), codes)


@pytest.mark.skipif(not nb.available(), reason="numba not importable or DIFFUSER_LAB_NUMBA=0")
def test_compiled_order_is_the_numpy_order():
    from diffuser_lab.backends.numba.morton import morton_order

    pts = tied_cloud(1)
    order, origin, step, _, q = morton_order(pts)
    qn, on, sn = quantize(pts)
    np.testing.assert_array_equal(q, qn)
    assert step == sn and np.array_equal(origin, on)
    assert_stable(order, morton_codes(qn))
    np.testing.assert_array_equal(order, spatial_order(pts))
