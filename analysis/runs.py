"""Finding and reading run folders: :mod:`diffuser_lab.runs.results` (the CLI prints the same sweep
table at the end of a sweep), re-exported for the analysis scripts."""
from diffuser_lab.runs.results import (  # noqa: F401 - re-exported
    SEED_KEYS,
    Run,
    experiment_name,
    find_runs,
    folder_name,
    is_nan,
    number,
    parse_overrides,
    scene_name,
    scenes,
)

__all__ = ["Run", "SEED_KEYS", "experiment_name", "find_runs", "folder_name", "is_nan", "number", "parse_overrides", "scene_name", "scenes"]
