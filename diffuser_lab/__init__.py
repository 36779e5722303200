"""diffuser-lab: multi-view 2D-to-3D semantic label diffusion (Mascaro et al., ICRA 2021).

The library face::

    from diffuser_lab import run, default_config, Scene, Frame, RunResult

    res = run(default_config(**{"graph.k": 16}))          # the demo room
    res = run(default_config(), scene=Scene(...))         # your own points and frames

The package reads in the order the data flows (imports point down this list, never up):

- ``data/``      what a run reads: the scene, its frames and their 2D labels (sources, rendering,
                 simulated or file predictions, class mappings, input checks)
- ``method/``    the paper: evidence (Eqs. 1-2, 11-13), graph (3-4), diffusion (10, 14-16), metrics,
                 and the straightforward scipy float64 reference
- ``backends/``  the hot loops: numba kernels (kNN, Eq. 4 weights, Jacobi steps) and torch (CUDA)
- ``recording/`` observers of a run: run.rrd (Rerun), run.mcap, the per-iteration statistics
- ``runs/``      one run and the protocols: config, pipeline, protocols, report, records, sweeps
- ``cli/``       the console scripts diffuser-lab, diffuser-lab-inspect, diffuser-lab-bench

and three modules every layer may use: ``config.py`` (the config schema, its ranges, the Hydra
store), ``hooks.py`` (the narrow interface through which recorders observe a run) and
``progress.py`` (progress lines on a terminal).
"""

__version__ = "0.1.0"
__all__ = ["run", "default_config", "Scene", "Frame", "RunResult", "Config"]

_FACE = {"run": "diffuser_lab.runs.pipeline", "RunResult": "diffuser_lab.runs.pipeline",
         "default_config": "diffuser_lab.runs.resolve", "Config": "diffuser_lab.config",
         "Scene": "diffuser_lab.data.scene", "Frame": "diffuser_lab.data.scene"}


def __getattr__(name: str):
    """The library face, imported on first use (``import diffuser_lab`` itself stays cheap)."""
    if name in _FACE:
        import importlib

        value = getattr(importlib.import_module(_FACE[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'diffuser_lab' has no attribute {name!r}")
