import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared"

# The suite compiles numba's kernels in the foreground: a CLI run in a subprocess would otherwise
# take the numpy/scipy path while the cache is cold (tests/cli/test_first_run.py covers that path).
os.environ.setdefault("DIFFUSER_LAB_NUMBA", "1")

# Small demo settings for tests that only need the mechanics (seconds, not tens of seconds).
SMALL_DEMO = ["scene.demo.n_views=10", "scene.demo.point_spacing=0.08", "solver.max_iter=60"]


def run_cli(*args: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run `diffuser-lab ARGS` as a user would (python -m diffuser_lab)."""
    e = dict(os.environ)
    e.pop("HYDRA_FULL_ERROR", None)
    e.update(env or {})
    return subprocess.run([sys.executable, "-m", "diffuser_lab", *args], cwd=cwd or ROOT, env=e,
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="session")
def small_demo_scene():
    from diffuser_lab.config import default_config
    from diffuser_lab.runs.pipeline import load_scene

    cfg = default_config(**{"scene.demo.n_views": 12, "scene.demo.point_spacing": 0.07})
    return load_scene(cfg.scene)


def compose(*overrides):
    """The validated config of ``diffuser-lab`` with these overrides (Hydra composes it from conf/)."""
    from hydra import compose as hcompose
    from hydra import initialize_config_dir

    from diffuser_lab.cli.main import config_dir
    from diffuser_lab.config import register, to_object

    register()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return to_object(hcompose("config", overrides=list(overrides)))
