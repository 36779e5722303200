"""diffuser_lab/seeding.py: every random draw of the package and of ``analysis/`` goes through it (an
``ast`` scan), each purpose the code draws for gives the first values it gave when the figures were
measured (literals: a numpy whose SeedSequence, PCG64 or distributions changed fails here, not in a
figure), and keys are independent (another purpose, id or seed: another stream; the same key: the
same draw, whatever else was drawn)."""
from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from diffuser_lab import seeding

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("diffuser_lab", "analysis", "hydra_plugins")

# seeding.rng(0, purpose).random(2)
RNG = {
    "analysis.paired.bootstrap": [0.515073051059009, 0.9057107235889045],
    "analysis.paired.flips": [0.23703143272595595, 0.4544288699894633],
    "bench.roof_matmul": [0.2220317685525236, 0.4727480418711758],
    "features.basis.sample": [0.8845407868915564, 0.3576577471584522],
    "predictions.blob_count": [0.41815289685099777, 0.44883473822393605],
    "predictions.blob_shapes": [0.8798962396512013, 0.13538805875245052],
    "predictions.features": [0.6958060442248453, 0.27520577365321164],
    "predictions.jitter": [0.0629488397571939, 0.5759397967604273],
    "records.feature_pca": [0.7325825156829618, 0.160181432678693],
    "records.point_radius": [0.8493506229047936, 0.4200801287403134],
    "tune.sampler": [0.6242785783117285, 0.6666052012593529],
}
# seeding.uniform(0, purpose, [0, 1])
UNIFORM = {
    "camera.eye": [0.4401064730349594, 0.7481021872317252],
    "camera.height": [0.3849388871577254, 0.8268231555872508],
    "camera.pitch": [0.7521234410846492, 0.03485478249179563],
    "camera.target": [0.6481058447824352, 0.3164466572868708],
    "camera.target_point": [0.7207518712495772, 0.03728529544474146],
    "predictions.blob": [0.3027723340928671, 0.8277320936505709],
    "predictions.cell": [0.7341748723925415, 0.34123919365198685],
    "predictions.component": [0.12408106697255972, 0.9868729803844029],
    "predictions.component_class": [0.764614133920409, 0.39850799227566547],
    "predictions.region": [0.3423878170020894, 0.37629654710479643],
    "predictions.region_class": [0.7804426373141594, 0.7108719811449885],
    "predictions.region_shown": [0.5790416272468238, 0.7874803407949519],
    "surface.count": [0.44809429551861524, 0.41187526085126],
    "surface.uv": [0.934627518616613, 0.039085526224979295],
    "workload.noise_vote": [0.36373147713280585, 0.6123896054826931],
}
# seeding.normal(0, purpose, [0, 1])
NORMAL = {
    "features.basis.probes": [-0.4223626730474587, -1.3598969456180716],
    "features.basis.range_finder": [0.3428169027861955, 0.2976866055313954],
    "surface.noise": [-0.9996569310134491, 1.12260733844205],
}
# seeding.integers(0, purpose, 20, [0, 1, 2, 3])
INTEGERS = {
    "workload.noise_class": [14, 15, 2, 3],
}
# seeding.keyed(purpose, *key).random(2): the streams that predate purposes, with a key of each's form
CHAIR = 9781291842197698363  # data.embeddings._name_seed("chair")
KEYED = {
    "demo.layout": ((0,), [0.6369616873214543, 0.2697867137638703]),
    "city.block": ((0, 1, 2, 0), [0.8817035384837327, 0.28917661385918403]),
    "city.views": ((0, 1, 2, 2), [0.9629475580598617, 0.501109034479212]),
    "sensor.frame": ((0, 3, 0x5E45), [0.09811274429349681, 0.8869548676445433]),
    "text.common": ((0, 0), [0.6369616873214543, 0.2697867137638703]),
    "text.class": ((0, 1, CHAIR), [0.7708145498853097, 0.6830565172929574]),
    "geometry.spacing": ((0,), [0.6369616873214543, 0.2697867137638703]),
    "sparse.sample": ((0,), [0.6369616873214543, 0.2697867137638703]),
}
FORMS = {"rng": RNG, "uniform": UNIFORM, "normal": NORMAL, "integers": INTEGERS, "keyed": KEYED}


def _files():
    for top in SCANNED:  # the package, analysis/ and the sweeper plugin: a few hundred files
        yield from sorted((ROOT / top).rglob("*.py"))


def _dotted(node: ast.AST) -> str:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        parts.append(node.id)
    return ".".join(reversed(parts))


def _draws_outside_seeding(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, what) of each generator made or draw taken other than through seeding.py: an import of
    ``random`` or ``numpy.random``, ``np.random`` used other than as the ``Generator`` type (in an
    annotation or isinstance), a call of a name ``default_rng``, a torch random function."""
    bad = []
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            bad += [(node.lineno, f"import {a.name}") for a in node.names
                    if a.name in ("random", "numpy.random") or a.name.startswith("numpy.random.")]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if mod == "random" or mod.startswith("numpy.random") or (
                    mod == "numpy" and any(a.name == "random" for a in node.names)):
                bad.append((node.lineno, f"from {mod} import ..."))
        elif isinstance(node, ast.Attribute) and _dotted(node) in ("np.random", "numpy.random"):
            up = parents.get(node)
            call = parents.get(up)
            made = isinstance(call, ast.Call) and call.func is up  # np.random.Generator(...): a generator made
            if not (isinstance(up, ast.Attribute) and up.attr == "Generator" and not made):
                bad.append((node.lineno, ast.unparse(up if isinstance(up, ast.Attribute) else node)))
        elif isinstance(node, ast.Call):
            name = _dotted(node.func)
            if name.split(".")[-1] == "default_rng" or name in (
                    "torch.manual_seed", "torch.rand", "torch.randn", "torch.randint", "torch.randperm", "torch.Generator"):
                bad.append((node.lineno, name))
    return sorted(set(bad))


def test_no_draw_outside_seeding():
    found = []
    for path in _files():
        if path == ROOT / "diffuser_lab" / "seeding.py":
            continue
        found += [f"{path.relative_to(ROOT)}:{line}: {what}" for line, what in _draws_outside_seeding(ast.parse(path.read_text()))]
    assert not found, "draws outside diffuser_lab/seeding.py (use seeding.rng / uniform / normal / integers):\n" + "\n".join(found)


def test_the_scan_finds_draws():
    code = ("import random\nfrom numpy.random import default_rng\nimport numpy as np\n"
            "a = np.random.default_rng(0)\nb = np.random.rand(3)\nr = np.random\nc = default_rng(1)\n"
            "def f(g: np.random.Generator) -> np.random.Generator:\n    return isinstance(g, np.random.Generator)\n"
            "d = np.random.Generator(np.random.PCG64(0))\n")
    lines = sorted({line for line, _ in _draws_outside_seeding(ast.parse(code))})
    assert lines == [1, 2, 4, 5, 6, 7, 10]  # the annotations and the isinstance (lines 8-9) are allowed


def _purposes_in_code() -> dict[str, set[str]]:
    """{form: purposes} of every ``seeding.<form>(...)`` call with a literal purpose; an f-string's
    literal prefix ends in "*"."""
    out: dict[str, set[str]] = {f: set() for f in FORMS}
    for path in _files():
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and _dotted(node.func.value) == "seeding" and node.func.attr in FORMS):
                continue
            i = 0 if node.func.attr == "keyed" else 1
            arg = node.args[i]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                out[node.func.attr].add(arg.value)
            elif isinstance(arg, ast.JoinedStr) and isinstance(arg.values[0], ast.Constant):
                out[node.func.attr].add(arg.values[0].value + "*")
            else:
                raise AssertionError(f"{path.relative_to(ROOT)}:{node.lineno}: a purpose that is not a literal")
    return out


def test_every_purpose_in_the_code_is_pinned():
    code = _purposes_in_code()
    for form, table in FORMS.items():
        names = set(table)
        for p in code[form]:
            if p.endswith("*"):  # analysis.paired.{what}: the test pins each what it is called with
                assert any(n.startswith(p[:-1]) for n in names), (form, p)
            else:
                assert p in names, f"seeding.{form}(..., {p!r}, ...) has no pinned values in tests/test_seeding.py"
        gone = {n for n in names if n not in code[form] and not any(c.endswith("*") and n.startswith(c[:-1]) for c in code[form])}
        assert not gone, f"pinned but drawn nowhere: {sorted(gone)}"
    assert set(KEYED) == set(seeding.KEYED)


@pytest.mark.parametrize("purpose", sorted(RNG))
def test_rng_first_draws(purpose):
    np.testing.assert_array_equal(seeding.rng(0, purpose).random(2), RNG[purpose])


@pytest.mark.parametrize("purpose", sorted(UNIFORM))
def test_uniform_first_draws(purpose):
    np.testing.assert_array_equal(seeding.uniform(0, purpose, np.arange(2)), UNIFORM[purpose])


@pytest.mark.parametrize("purpose", sorted(NORMAL))
def test_normal_first_draws(purpose):
    np.testing.assert_array_equal(seeding.normal(0, purpose, np.arange(2)), NORMAL[purpose])


def test_integers_first_draws():
    for purpose, want in INTEGERS.items():
        np.testing.assert_array_equal(seeding.integers(0, purpose, 20, np.arange(4)), want)


@pytest.mark.parametrize("purpose", sorted(KEYED))
def test_keyed_first_draws(purpose):
    key, want = KEYED[purpose]
    np.testing.assert_array_equal(seeding.keyed(purpose, *key).random(2), want)
    np.testing.assert_array_equal(np.random.default_rng(list(key)).random(2), want)  # the call it replaced


def test_keyed_streams_are_their_call_sites_draws():
    from diffuser_lab.data.embeddings import _name_seed
    from diffuser_lab.data.sensor import SensorModel

    assert _name_seed("chair") == CHAIR
    np.testing.assert_array_equal(SensorModel(seed=0).rng(3).random(2), KEYED["sensor.frame"][1])
    np.testing.assert_array_equal(np.random.default_rng(0).random(2), KEYED["demo.layout"][1])  # default_rng(seed)
    with pytest.raises(KeyError, match="seeding.rng"):
        seeding.keyed("demo.layoutt", 0)


def test_the_distributions_the_code_draws():
    """Generator methods the package calls, on one key: numpy may change a distribution's algorithm
    between versions (NEP 19); this fails first."""
    g = seeding.rng(0, "test.distributions")
    assert g.random(2).tolist() == [0.9789628073887626, 0.8957339544382871]
    assert g.uniform(-1, 1, 2).tolist() == [-0.1273260004580008, -0.39896773316676426]
    assert g.normal(1, 2, 2).tolist() == [3.47907639190133, 4.121103099997349]
    assert g.standard_normal(2).tolist() == [0.0052639620982201174, -1.2168919765418793]
    assert g.integers(0, 100, 3).tolist() == [60, 73, 62]
    assert g.choice(100, 3, replace=False).tolist() == [80, 43, 70]
    assert g.choice([-1.0, 1.0], 3).tolist() == [1.0, 1.0, 1.0]
    assert g.poisson(3.0, 3).tolist() == [4, 3, 2]


def test_counter_core_is_pinned():
    assert seeding.purpose_id("demo.layout") == 215598854
    assert [int(h) for h in seeding.hash64(0, 1, np.arange(3))] == [14816053939101234323, 4618857875736427910,
                                                                     1729233307704022544]


def test_keys_are_independent():
    firsts = [v[0] for v in RNG.values()] + [v[0] for v in UNIFORM.values()] + [v[0] for v in NORMAL.values()]
    assert len(set(firsts)) == len(firsts)  # every purpose its own stream
    a = seeding.rng(0, "records.point_radius").random(4)
    for other in (seeding.rng(1, "records.point_radius"), seeding.rng(0, "records.feature_pca"),
                  seeding.rng(0, "records.point_radius", 1), seeding.rng((0, 1), "records.point_radius")):
        assert not np.isin(other.random(4), a).any()
    np.testing.assert_array_equal(seeding.rng([0], "records.point_radius").random(4), a)  # an int is a 1-int key


def test_a_counter_draw_depends_on_its_key_alone():
    ids = np.arange(1000)
    u = seeding.uniform(7, "surface.uv", ids, 1)
    assert ((u > 0) & (u < 1)).all() and len(np.unique(u)) == 1000
    np.testing.assert_array_equal(u[[3, 999]], [seeding.uniform(7, "surface.uv", 3, 1), seeding.uniform(7, "surface.uv", 999, 1)])
    for other in (seeding.uniform(8, "surface.uv", ids, 1), seeding.uniform(7, "surface.count", ids, 1),
                  seeding.uniform(7, "surface.uv", ids, 2), np.delete(seeding.uniform(7, "surface.uv", 1, ids), 1)):
        assert not np.isin(other, u).any()  # the last: the ids swapped, (1, 1) left out
    assert abs(float(seeding.normal(7, "surface.noise", ids).mean())) < 0.1
    k = seeding.integers(7, "workload.noise_class", 5, ids)
    assert k.min() == 0 and k.max() == 4
