"""Fill numba's on-disk cache in two processes at once before pytest-xdist's workers start, when it
is empty (a fresh clone: CI). Otherwise each worker, and each command line it starts, compiles the
same kernels at the same time (~50 s on one core each: measured 560 s for the suite cold, 496 s warm).

``python tests/prewarm.py graph``: the batch kNN graph's kernels (grid kNN with and without normals,
Eq. 4 weights; then :func:`systems`), ~30 s. ``python tests/prewarm.py rest``: :func:`diffuser_lab.cli.warm.warm`'s runs
with the graph built on the scipy path (so the two do not compile the same kernels), ~30 s.
tests/conftest.py starts both and the scheduler waits for them.
"""
from __future__ import annotations

import functools
import sys


def graph() -> None:
    from diffuser_lab.data.sources.demo import make_demo_scene
    from diffuser_lab.method.graph import build_graph

    scene, _ = make_demo_scene(n_views=1, point_spacing=0.1)
    build_graph(scene.points, 24, scene.normals, backend="numba")
    build_graph(scene.points, 24, None, backend="numba")
    build_graph(scene.points, 24, scene.normals, invariant_normals=True, backend="numba")
    systems()


def systems() -> None:
    """The Jacobi kernels of the other class widths, the sparse class set and GMRES
    (online.solver=gmres): the suite's runs use them besides a default run's."""
    import numpy as np

    from diffuser_lab.method.diffusion import diffuse, normalise
    from diffuser_lab.method.graph import build_graph

    rng = np.random.default_rng(0)
    pts = rng.random((400, 3)).astype(np.float32)
    g = build_graph(pts, 8, None, backend="scipy")
    for c, sparse in ((8, "off"), (24, "off"), (32, "off"), (40, "on")):
        mass = np.zeros((400, c), np.float32)
        mass[np.arange(400), rng.integers(0, c, 400)] = 1
        diffuse(normalise(g, mass, 1e-4), max_iter=3, backend="numba", sparse_classes=sparse)
        if c <= 24:  # online.solver=gmres
            system = normalise(g, mass, 1e-4)
            system.start(backend="numba")
            system.krylov(3)
            system.close()


def rest() -> None:
    from diffuser_lab.cli import warm
    from diffuser_lab.method import graph as graph_mod

    graph_mod.build_graph = functools.partial(graph_mod.build_graph, backend="scipy")
    warm.warm()


if __name__ == "__main__":
    {"graph": graph, "rest": rest}[sys.argv[1]]()
