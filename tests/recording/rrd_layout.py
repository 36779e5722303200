"""What every run.rrd's layout must hold, read back from the file (issue 41): its kind's
application id, a ``legend`` view of the ``legend`` entity (a picture, and as values the classes
present, ``unlabeled``, in the taxonomy's colours) and its plots' contents. Shared by the batch, online and tiled tests,
on the runs they already record."""
from pathlib import Path

import numpy as np
from test_viewer import chunks, views

from diffuser_lab.recording.rerun_log import unlabeled_color


def app_id(path: Path) -> str:
    from rerun.chunk import RrdReader

    r = RrdReader(path)
    (app,) = {s.application_id for s in [*r.recordings(), *r.blueprints()]}
    return app


def static_column(path: Path, entity: str, column: str):
    """The last value of a static column of ``entity``."""
    for ch in chunks(path):
        if ch.entity_path == entity and ch.is_static:
            return ch.to_record_batch().column(column).to_pylist()[-1]
    raise KeyError(entity)


def legend(path: Path) -> dict:
    """{name: (r, g, b)} of the legend's entries (its values beside its picture)."""
    names = static_column(path, "/legend", "classes")
    packed = static_column(path, "/legend", "colors")
    img = static_column(path, "/legend", "Image:buffer")
    assert np.asarray(img).size > 10_000  # the picture
    return {n: ((c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255) for n, c in zip(names, packed)}


def check_layout(path: Path, app: str, taxonomy, present, plots: dict) -> dict:
    """Asserts the common part; ``present``: class ids that must be in the legend; ``plots``
    {view name: [entity paths]} that the blueprint must hold. Returns :func:`views`."""
    assert app_id(path) == app
    v = views(path)
    assert v["legend"]["query"] == ["/legend"]
    leg = legend(path)
    assert leg.pop("unlabeled") == unlabeled_color(taxonomy.colors)
    leg.pop("wrong label", None)
    for c in np.unique(present):
        assert leg[taxonomy.names[c]] == tuple(int(x) for x in taxonomy.colors[c])
    for name, contents in plots.items():
        assert v[name]["query"] == contents, name
    return v
