"""summary.json's provenance block: well-formed, cached, cheap, no commit outside a git checkout
without an error, and the differences between blocks named field by field."""
import copy
import subprocess
import time

import numpy as np
import pytest
from conftest import check_provenance

from diffuser_lab.backends import provenance


def test_the_block_is_well_formed_cached_and_cheap(record_property):
    provenance._collect.cache_clear()
    t = time.perf_counter()
    b = provenance.collect()
    first_ms = 1e3 * (time.perf_counter() - t)
    t = time.perf_counter()
    again = provenance.collect()
    record_property("provenance_first_ms", round(first_ms, 1))  # measured, not asserted (benchmarks time)
    record_property("provenance_cached_ms", round(1e3 * (time.perf_counter() - t), 3))
    check_provenance(b)
    assert again == b and again is not b  # a copy: a caller's change stays its own
    again["machine"]["cpu_model"] = "changed"
    assert provenance.collect()["machine"]["cpu_model"] == b["machine"]["cpu_model"]
    assert b["versions"]["numpy"] == np.__version__
    if b["machine"]["numba"] is not None:  # numba's target: its features decide the ISA level
        assert (b["machine"]["isa"] == "avx512") == b["machine"]["numba"]["avx512"] or not b["machine"]["numba"]["enabled"]


def test_outside_a_git_checkout_the_commit_is_null(tmp_path, monkeypatch):
    assert provenance.git_state(tmp_path) == (None, None)  # no .git: git is not even started
    (tmp_path / ".git").write_text("gitdir: /nowhere\n")  # a broken worktree link: git fails
    assert provenance.git_state(tmp_path) == (None, None)
    monkeypatch.setattr(provenance, "ROOT", tmp_path / "site-packages")  # the package installed, not checked out
    provenance._collect.cache_clear()
    try:
        d = provenance.collect()["diffuser_lab"]
        assert d["commit"] is None and d["dirty"] is None
    finally:
        provenance._collect.cache_clear()


def test_a_checkouts_commit_and_dirty_tree(tmp_path):
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    subprocess.run([*git, "init", "-q"], check=True)
    assert provenance.git_state(tmp_path) == (None, None)  # no commit yet
    (tmp_path / "a.py").write_text("x = 1\n")
    subprocess.run([*git, "add", "a.py"], check=True)
    subprocess.run([*git, "commit", "-qm", "a"], check=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    assert provenance.git_state(tmp_path) == (head, False)
    (tmp_path / "a.py").write_text("x = 2\n")
    assert provenance.git_state(tmp_path) == (head, True)


def _other(block: dict, cpu: str = None, numpy: str = None, isa: str = None) -> dict:
    b = copy.deepcopy(block)
    if cpu:
        b["machine"]["cpu_model"] = cpu
    if isa:
        b["machine"]["isa"] = isa
    if numpy:
        b["versions"]["numpy"] = numpy
    return b


def test_differences_name_the_fields_and_count_the_runs():
    here = provenance.collect()
    amd = _other(here, cpu="AMD EPYC 7742 64-Core Processor", isa="avx2")
    old = _other(here, numpy="1.26.4")
    assert provenance.differences([here, copy.deepcopy(here), None]) == []  # a run without a block is left out
    assert provenance.differences_line([here, here]) is None
    assert provenance.key(here) == provenance.key(copy.deepcopy(here)) != provenance.key(amd)
    assert [f for f, _, _ in provenance.blocks_differ(here, amd)] == ["CPU", "ISA"]
    assert provenance.blocks_differ(here, None) == []
    diffs = provenance.differences([here, here, amd, old])
    assert [d.fields for d in diffs] == [("CPU", "ISA"), ("numpy",)]  # CPU and ISA split the runs alike
    assert diffs[0].counts == ((here["machine"]["cpu_model"], 3), ("AMD EPYC 7742 64-Core Processor", 1))
    line = provenance.differences_line([here, here, amd, old])
    assert line == (f"mixed machines or versions: CPU {here['machine']['cpu_model']} (3 jobs), AMD EPYC 7742 "
                    f"64-Core Processor (1 job) (with it: ISA); numpy {here['versions']['numpy']} (3 jobs), "
                    f"1.26.4 (1 job)")
    assert provenance.differences_line([here, old], "runs") == \
        f"mixed machines or versions: numpy {here['versions']['numpy']} (1 run), 1.26.4 (1 run)"


def test_summary_line_says_where():
    b = provenance.collect()
    line = provenance.summary_line(b)
    assert line.startswith(f"{b['machine']['cpu_model']} ({b['machine']['isa']}), numpy {b['versions']['numpy']}")
    assert provenance.summary_line(None) == "not recorded"


@pytest.mark.parametrize("features,isa", [("+avx2,+fma,-avx512f,+avx", "avx2"), ("-avx2,+sse4.2", "sse4.2"),
                                          ("+neon", "neon"), ("", "baseline")])
def test_isa_level_of_numbas_features(monkeypatch, features, isa):
    monkeypatch.setitem(provenance._FEATURES, "numba", {f[1:] for f in features.split(",") if f.startswith("+")})
    assert provenance._isa({"enabled": True}) == isa
