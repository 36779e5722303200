"""The feature evidence's two per-pixel passes where the compiled kernels run
(:mod:`diffuser_lab.backends.numba.features`): the best view's confidence rows and the bilinear
sample in a basis with its adds. Each returns None where the kernels are off (the caller's numpy
path then runs: :func:`diffuser_lab.method.features.top_probability`,
:func:`diffuser_lab.method.evidence.sample_basis`); both give the same bits."""
from __future__ import annotations

from typing import Optional

import numpy as np

from . import numba as nb


def available() -> bool:
    """Whether the compiled kernels run (:func:`diffuser_lab.backends.numba.available`)."""
    return nb.available()


def top_probability_rows(e: np.ndarray, to_class: np.ndarray, num_classes: int) -> Optional[np.ndarray]:
    """(M, Q) float32 C-contiguous ``exp((cos - 1) / T)`` (NaN: no feature, taken as 0) -> (M,)
    float32 each row's top class share, or None without the compiled kernels."""
    if not nb.available() or e.shape[0] == 0:
        return None
    from .numba import features as compiled

    return compiled.top_probability(e, to_class, num_classes)


def sample_add(coords: np.ndarray, gram: np.ndarray, valid: np.ndarray, fshape: tuple[int, int],
               shape: tuple[int, int], rows: np.ndarray, cols: np.ndarray, idx: np.ndarray, mass: np.ndarray,
               links: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """The bilinear samples of a projected map and their adds to ``mass``/``links`` rows ``idx`` in
    one compiled pass (:func:`diffuser_lab.backends.numba.features.sample_add`), or None without
    the compiled kernels or for arrays they do not take (mass not float32 C-contiguous)."""
    if not nb.available() or not (mass.flags.c_contiguous and mass.dtype == np.float32
                                  and links.flags.c_contiguous and coords.flags.c_contiguous
                                  and gram.flags.c_contiguous):
        return None
    from .numba import features as compiled

    return compiled.sample_add(coords, gram, valid, fshape, shape, rows, cols, idx, mass, links)
