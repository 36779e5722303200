"""open3d, imported on first use and without its plotly/dash viewer.

``import open3d`` imports ``open3d.visualization.draw_plotly``, which imports dash, plotly and
IPython: ~0.4 s of a command's ~2 s start-up, for a web viewer diffuser-lab never opens. Until the
first call of one of its three functions, that module is a stand-in whose functions import the real
one and call it, so a user's ``open3d.visualization.draw_plotly(...)`` still works.
"""
from __future__ import annotations

import importlib
import sys
import types

_PLOTLY = "open3d.visualization.draw_plotly"
_PLOTLY_NAMES = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _real_plotly(name: str):
    def call(*args, **kwargs):
        if getattr(sys.modules.get(_PLOTLY), "_diffuser_lab_stand_in", False):
            del sys.modules[_PLOTLY]
        real = importlib.import_module(_PLOTLY)
        vis = sys.modules["open3d.visualization"]
        for n in _PLOTLY_NAMES:  # later calls go straight to the real functions
            setattr(vis, n, getattr(real, n))
        return getattr(real, name)(*args, **kwargs)

    call.__name__ = name
    return call


def open3d():
    """The ``open3d`` module (see the module docstring for what is deferred)."""
    if "open3d" not in sys.modules and _PLOTLY not in sys.modules:
        stand_in = types.ModuleType(_PLOTLY)
        stand_in._diffuser_lab_stand_in = True
        for n in _PLOTLY_NAMES:
            setattr(stand_in, n, _real_plotly(n))
        sys.modules[_PLOTLY] = stand_in
    import open3d as o3d

    return o3d
