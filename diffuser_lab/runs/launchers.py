"""Our defaults for two Hydra launcher plugins whose option names we keep as the plugins spell them.

``hydra/launcher=ray`` and ``hydra/launcher=submitit_local`` are the plugins' own configs. A
YAML file of the same name under ``conf/hydra/launcher/`` would hide the plugin's config (a
``defaults: [ray]`` in it includes itself) and is matched against the plugin's schema by a
mechanism Hydra deprecated, so the changed defaults are stored here over the plugins' ones,
in the ConfigStore, before Hydra composes anything:

- ``ray``: a local Ray instance unless ``hydra.launcher.ray.init.address`` says otherwise
  (``auto`` joins a running cluster), no dashboard, one CPU per job
  (``hydra.launcher.ray.remote.num_cpus=2`` for more; the job's kernels use that many threads);
  the jobs' output stays in Ray's logs, their one-line results are printed from their
  summaries (:mod:`diffuser_lab.runs.sweep`).
- ``submitit_local``: submitit's files in ``<sweep dir>/.submitit/`` (the plugin's
  ``.submitit/%j`` made submitit's local executor create a literal ``%j`` folder), one CPU per job.

The other launcher configs (``local_parallel``, ``slurm``) are YAML files in ``conf/hydra/launcher/``.
"""
from __future__ import annotations

import importlib.util


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def register() -> None:
    """Store the changed defaults (only for the plugins that are installed)."""
    from hydra.core.config_store import ConfigStore
    from hydra.core.plugins import Plugins

    Plugins.instance()  # Hydra's one scan of the plugins runs their store() calls: ours must come after
    cs = ConfigStore.instance()
    if _installed("hydra_plugins.hydra_ray_launcher"):
        from hydra_plugins.hydra_ray_launcher._config import RayConf, RayLauncherConf

        cs.store(group="hydra/launcher", name="ray", provider="diffuser_lab",
                 node=RayLauncherConf(ray=RayConf(init={"address": None, "include_dashboard": False,
                                                        "log_to_driver": False},
                                                  remote={"num_cpus": 1})))
    if _installed("hydra_plugins.hydra_submitit_launcher"):
        from hydra_plugins.hydra_submitit_launcher.config import LocalQueueConf

        cs.store(group="hydra/launcher", name="submitit_local", provider="diffuser_lab",
                 node=LocalQueueConf(submitit_folder="${hydra.sweep.dir}/.submitit", cpus_per_task=1))
