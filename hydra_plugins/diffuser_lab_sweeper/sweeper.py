"""Hydra's basic sweeper (the same jobs, in the same order, the same launchers) with a cheaper
start-up check: before launching, the basic sweeper composes the config of *every* job to find a
bad override early, then the launcher composes each job again (~0.16 s a compose here: a third of
a small job's time). This one composes only jobs that together hold every override of the sweep:
every value of every swept key is still checked before any job runs (a typo, an unknown key, a
value of the wrong type stops the sweep at start-up), and a 5 x 3 sweep composes 5 configs up
front, not 15. The jobs' composes then share one cache of the config files (a fifth of a small
sweep's time).

With ``hydra.sweeper.tune`` set (an experiment's config: ``+experiment=tune_tikhonov``) it runs a
parameter search instead of the grid: Optuna trials on validation jobs, the best written as a
preset, then the held-out test jobs (:mod:`diffuser_lab.runs.tune`, docs/sweeps.md "Tuning"; the
``tune`` extra). A section of this sweeper rather than a sweeper of its own: conf/config.yaml
chooses this one, and a choice of the primary config's defaults list is not overridden from an
experiment's. Not Hydra's Optuna sweeper (hydra-optuna-sweeper): its last release, 1.3.0, requires
optuna<3, and its trial is one job, where a trial here is the mean over several validation jobs
followed by jobs held out from the search.

No ``from __future__ import annotations`` here: Hydra's plugin scan runs this file outside
``sys.modules``, where a dataclass needs evaluated annotations.
"""
import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from hydra._internal.config_repository import CachingConfigRepository
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf


@dataclass
class CoveringSweeperConf:
    _target_: str = "hydra_plugins.diffuser_lab_sweeper.sweeper.CoveringSweeper"
    max_batch_size: Optional[int] = None
    params: Optional[Dict[str, str]] = None
    tune: Optional[Dict[str, Any]] = None  # a parameter search's keys (diffuser_lab/runs/tune.py); null: the grid


ConfigStore.instance().store(group="hydra/sweeper", name="diffuser_lab", node=CoveringSweeperConf,
                             provider="diffuser_lab")


def covering(batch: Sequence[Sequence[str]]) -> List[Sequence[str]]:
    """Jobs of ``batch`` (each a list of ``key=value`` overrides) that together hold every override
    of the batch, picked greedily by how many overrides not yet held each brings (ties: the earlier
    job), in batch order: for a 5 x 3 grid, 5 jobs."""
    left = {o for job in batch for o in job}
    picked = []
    while left:
        best = max(range(len(batch)), key=lambda i: (len(left.intersection(batch[i])), -i))
        picked.append(best)
        left.difference_update(batch[best])
    return [batch[i] for i in sorted(picked)]


class _CopyingRepository(CachingConfigRepository):
    """A CachingConfigRepository whose cached files are handed out as deep copies: Hydra merges a
    ``@package _global_`` option (method=ldls's ``graph.k: 10``) into the loaded nodes of other
    groups in place, so a shared node carried one job's values into the next (every Diffuser job of
    a sweep with an LDLS job ran LDLS's graph: K = 10, no normals)."""

    def load_config(self, config_path):
        return copy.deepcopy(super().load_config(config_path))


class _OneRepository:
    """Stands in for ``ConfigLoaderImpl._parse_overrides_and_create_caching_repo``, which deep-copies
    the config repository and reads every YAML file again for each job's compose (~a third of it):
    the jobs of one sweep share one caching repository per search path, which hands out copies of
    the files it read (:class:`_CopyingRepository`). A picklable object, for the launchers that ship
    the loader to other processes."""

    def __init__(self, loader) -> None:
        from hydra.core.override_parser.overrides_parser import OverridesParser

        self.loader, self.parser, self.repos, self.files = loader, OverridesParser.create(), {}, {}

    def __call__(self, config_name, overrides):
        parsed = self.parser.parse_overrides(overrides=overrides)
        key = tuple(o for o in overrides if o.lstrip("+~").startswith("hydra.searchpath"))
        if key not in self.repos:
            self.repos[key] = _CopyingRepository(self.loader.repository)
        self.loader._process_config_searchpath(config_name, parsed, self.repos[key])
        return parsed, self.repos[key]


class CoveringSweeper(BasicSweeper):
    """:class:`BasicSweeper` whose :meth:`validate_batch_is_legal` composes :func:`covering`'s jobs
    and whose jobs' composes share one config repository (:class:`_OneRepository`); with ``tune``,
    the search of :func:`diffuser_lab.runs.tune.search` on the same launcher."""

    def __init__(self, max_batch_size: Optional[int] = None, params: Optional[Dict[str, str]] = None,
                 tune: Optional[Dict[str, Any]] = None) -> None:
        super().__init__(max_batch_size=max_batch_size, params=params)
        self.tune = tune

    def setup(self, *, hydra_context, task_function, config) -> None:
        super().setup(hydra_context=hydra_context, task_function=task_function, config=config)
        loader = hydra_context.config_loader
        if all(hasattr(loader, a) for a in ("_parse_overrides_and_create_caching_repo",
                                            "_process_config_searchpath", "repository")):
            loader._parse_overrides_and_create_caching_repo = _OneRepository(loader)  # else: Hydra's own

    def validate_batch_is_legal(self, batch: Sequence[Sequence[str]]) -> None:
        super().validate_batch_is_legal(covering(batch))

    def sweep(self, arguments: List[str]) -> Any:
        if self.tune is None:
            return super().sweep(arguments)
        from diffuser_lab.runs import tune

        if self.params:
            raise tune.TuneError(f"hydra.sweeper.params {dict(self.params)} with hydra.sweeper.tune: a search's "
                                 f"swept keys are hydra.sweeper.tune.params")
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        name = str(self.config.hydra.runtime.choices.get("experiment") or "best")
        return tune.search(tune.TuneSpec(**self.tune), arguments,
                           lambda jobs, idx: self.launcher.launch(jobs, initial_job_idx=idx),
                           self.validate_batch_is_legal, sweep_dir, name)
