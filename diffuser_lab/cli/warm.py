"""Fill numba's kernel cache: one small demo run with recording into a temporary folder, so the
kernels a default run uses (kNN graph, evidence, Jacobi steps for the demo's classes, the
recorders' per-iteration pass and the Z encodings of the default record) and those of
protocol=online are compiled and cached on disk.

``python -m diffuser_lab.cli.warm [LOCK]`` (what
:func:`diffuser_lab.backends.numba.compile_in_background` starts; ``LOCK`` is removed at the
end). Takes ~25 s on an empty cache, ~2 s on a warm one.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from diffuser_lab.backends import numba as nb
from diffuser_lab.recording import make_hooks
from diffuser_lab.runs.online import online
from diffuser_lab.runs.pipeline import run
from diffuser_lab.runs.resolve import default_config


def warm() -> None:
    """Compile (or load) the kernels of a default run, writing nothing outside a temporary folder."""
    nb.undefer()
    if not nb.available():
        return
    # 12 iterations: 1, 2, 5, 10 in the default q8 shares, the last (12) float32, class-major
    cfg = default_config(**{"n_views": 4, "solver.max_iter": 12})
    with tempfile.TemporaryDirectory(prefix="diffuser-lab-warm-") as d:
        hooks = make_hooks(cfg, Path(d))
        try:
            run(cfg, hooks=hooks)
        finally:
            hooks.close()
    # protocol=online (its kernels; both map modes, without the batch comparison)
    for mode in ("given", "growing"):
        oc = default_config(**{"n_views": 3, "protocol.name": "online", "online.map": mode,
                               "online.compare_batch": False, "record.mode": "off"})
        online(oc)


def main(argv: list[str]) -> None:
    try:
        warm()
    finally:
        if argv:
            Path(argv[0]).unlink(missing_ok=True)


if __name__ == "__main__":
    main(sys.argv[1:])
