"""Where a run ran: the machine, the instruction set the kernels use and the versions that decide its
figures (summary.json ``provenance``), and which of these differ between runs.

The same seed gave different figures on an AVX-512 and an AVX2 machine (numba's kernels, numpy's
dispatched loops and OpenBLAS all pick their code by the CPU), so every run records them
(:func:`collect`, a plain dict) and the tables that put runs side by side say when they differ
(:func:`differences`, :func:`flat`). Collected once per process and cached (about 20 ms the first
time, mostly the package versions and OpenBLAS's description, while one ``git status`` runs
beside them; nothing is imported to read a version).
"""
from __future__ import annotations

import copy
import functools
import hashlib
import importlib.metadata
import json
import os
import platform
import socket
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Optional

from . import numba as nb

DISTRIBUTIONS = ("numpy", "scipy", "open3d", "numba", "llvmlite", "rerun-sdk", "hydra-core", "omegaconf", "torch")
"""The distributions whose versions decide a run's figures (torch: ``solver.backend=torch``); read
with importlib.metadata (importing open3d to ask costs ~0.5 s); None when not installed."""

ISA_LEVELS = (("avx512f", "avx512"), ("avx2", "avx2"), ("avx", "avx"), ("sse4.2", "sse4.2"),
              ("sve", "sve"), ("neon", "neon"))
"""LLVM feature -> the ISA level it names, widest first (the first one on is the level)."""

NUMPY_ISA = (("AVX512F", "avx512"), ("AVX2", "avx2"), ("AVX", "avx"), ("SSE42", "sse4.2"), ("SVE", "sve"),
             ("ASIMD", "neon"), ("NEON", "neon"))
"""numpy's runtime feature -> ISA level, for a process without numba (the kernels are numpy's then)."""

FIELDS: tuple[tuple[str, str], ...] = (
    ("machine.cpu_model", "CPU"),
    ("machine.cpu_vendor", "vendor"),
    ("machine.isa", "ISA"),
    ("machine.numba.target", "numba target"),
    ("machine.numba.avx512", "numba AVX-512"),
    ("machine.numba.avx2", "numba AVX2"),
    ("machine.numba.fma", "numba FMA"),
    ("machine.numpy_simd.baseline", "numpy SIMD baseline"),
    ("machine.numpy_simd.dispatched", "numpy SIMD dispatched"),
    ("machine.blas", "BLAS"),
    ("machine.arch", "arch"),
    ("machine.libc", "libc"),
    ("machine.cpus_usable", "CPUs usable"),
    ("versions.python", "python"),
    *((f"versions.{d}", d) for d in DISTRIBUTIONS),
    ("diffuser_lab.version", "diffuser-lab"),
    ("diffuser_lab.commit", "commit"),
    ("diffuser_lab.dirty", "dirty tree"),
)
"""The compared fields (dotted path in the block, the name a table gives it), in the order a table
names them. Not compared: ``host`` (nodes of one kind give the same figures), ``machine.cpus``
(the machine's total: ``cpus_usable`` is what the run had), ``machine.numba.host``,
``machine.numba.env_cpu_name`` and ``machine.numba.enabled`` (what they change shows in
``numba.target`` and the features)."""


ROOT = Path(__file__).resolve().parents[2]
"""The folder holding ``diffuser_lab/``: a git checkout's top when the package is run from one."""


@functools.lru_cache(maxsize=1)
def _collect() -> dict:
    git = _git_start(ROOT)  # runs while the rest is read (~6 ms of the ~20)
    try:
        machine, versions = _machine(), _versions()
    finally:
        commit, dirty = _git_finish(git)
    return {
        "host": socket.gethostname(),
        "machine": machine,
        "versions": versions,
        "diffuser_lab": {"version": _version("diffuser-lab"), "commit": commit, "dirty": dirty},
    }


def collect() -> dict:
    """This process's provenance block (a fresh copy of the cached one; JSON-ready)::

        host                      the node's name
        machine.cpu_model         /proc/cpuinfo ``model name`` (else platform.processor())
        machine.cpu_vendor        ``vendor_id`` (GenuineIntel, AuthenticAMD, ...)
        machine.arch, .libc       x86_64 / aarch64; ``glibc 2.36``
        machine.cpus              CPUs of the machine; ``cpus_usable``: those this process may use
        machine.isa               the widest vector ISA the kernels use: avx512, avx2, avx, sse4.2,
                                  sve, neon or baseline (numba's target features; numpy's without numba)
        machine.numba             ``target`` (the CPU name numba compiles for: NUMBA_CPU_NAME or
                                  llvmlite's host), ``host`` (llvmlite's), ``env_cpu_name``
                                  (NUMBA_CPU_NAME or None), ``avx512``/``avx2``/``fma`` (in the target
                                  features), ``enabled`` (DIFFUSER_LAB_NUMBA); None without numba
        machine.numpy_simd        ``baseline`` (compiled in) and ``dispatched`` (chosen at run time,
                                  those this CPU has) of numpy's SIMD targets
        machine.blas              one per BLAS library loaded (numpy's and scipy's OpenBLAS): library
                                  (whose copy), internal_api, version, architecture (OpenBLAS's core
                                  type), threading_layer (threadpoolctl)
        versions                  python and :data:`DISTRIBUTIONS` (None: not installed)
        diffuser_lab              version, commit (git HEAD of the checkout the package was imported
                                  from; None outside a git checkout) and dirty (uncommitted changes or
                                  untracked files, None without a commit)
    """
    return copy.deepcopy(_collect())


def _machine() -> dict:
    model, vendor = _cpuinfo()
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        usable = os.cpu_count()
    numba_info = _safe(_numba, None)
    return {
        "cpu_model": model,
        "cpu_vendor": vendor,
        "arch": platform.machine() or None,
        "libc": _libc(),
        "cpus": os.cpu_count(),
        "cpus_usable": usable,
        "isa": _safe(lambda: _isa(numba_info), None),
        "numba": numba_info,
        "numpy_simd": _safe(_numpy_simd, None),
        "blas": _safe(_blas, []),
    }


def _safe(read, default):
    """A part that cannot be read is left unknown: provenance never fails a run."""
    try:
        return read()
    except Exception:  # noqa: BLE001 - a library's introspection that changed or broke
        return default


def _cpuinfo() -> tuple[Optional[str], Optional[str]]:
    """(model name, vendor) of the first CPU in /proc/cpuinfo; platform.processor() elsewhere."""
    model = vendor = None
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:  # the first processor's lines are enough
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name" and model is None:
                    model = value.strip()
                elif key in ("vendor_id", "CPU implementer") and vendor is None:
                    vendor = value.strip()
                elif not line.strip() and (model or vendor):
                    break
    except OSError:
        pass
    return model or platform.processor() or None, vendor


def _libc() -> Optional[str]:
    try:
        return os.confstr("CS_GNU_LIBC_VERSION")
    except (AttributeError, ValueError, OSError):
        return None


_FEATURES: dict[str, set] = {}  # the target features' "+name" entries, for _isa


def _numba() -> Optional[dict]:
    """numba's compile target: the CPU name and features its code generator passes to LLVM."""
    try:
        import llvmlite.binding as ll
        from numba.core import codegen, config
    except ImportError:
        return None
    host = ll.get_host_cpu_name()
    feats = config.CPU_FEATURES if config.CPU_FEATURES is not None else codegen.get_host_cpu_features()
    on = {f[1:] for f in str(feats).split(",") if f.startswith("+")}
    _FEATURES["numba"] = on
    return {"target": config.CPU_NAME or host, "host": host, "env_cpu_name": os.environ.get("NUMBA_CPU_NAME"),
            "avx512": "avx512f" in on, "avx2": "avx2" in on, "fma": "fma" in on, "enabled": nb.NB is not None}


def _isa(numba_info: Optional[dict]) -> str:
    if numba_info is not None and numba_info["enabled"]:
        on = _FEATURES.get("numba", set())
        return next((level for feat, level in ISA_LEVELS if feat in on), "baseline")
    feats = _numpy_features()
    return next((level for feat, level in NUMPY_ISA if feats.get(feat)), "baseline")


def _numpy_module():
    try:
        from numpy._core import _multiarray_umath as m  # numpy >= 2
    except ImportError:
        from numpy.core import _multiarray_umath as m
    return m


def _numpy_features() -> dict:
    return dict(getattr(_numpy_module(), "__cpu_features__", {}))


def _numpy_simd() -> dict:
    """What np.show_runtime() lists: the baseline targets and the dispatched ones this CPU has."""
    m = _numpy_module()
    feats = getattr(m, "__cpu_features__", {})
    return {"baseline": list(getattr(m, "__cpu_baseline__", [])),
            "dispatched": [f for f in getattr(m, "__cpu_dispatch__", []) if feats.get(f)]}


def _blas() -> list[dict]:
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return []
    seen, out = set(), []
    for lib in threadpool_info():
        if lib.get("user_api") != "blas":
            continue
        folder = Path(lib.get("filepath") or "").parent.name  # numpy.libs, scipy.libs: whose copy it is
        entry = {"library": folder[: -len(".libs")] if folder.endswith(".libs") else folder,
                 **{k: lib.get(k) for k in ("internal_api", "version", "architecture", "threading_layer")}}
        key = json.dumps(entry, sort_keys=True)
        if key not in seen:  # one shared library (a conda environment's) counts once
            seen.add(key)
            out.append(entry)
    return sorted(out, key=lambda e: json.dumps(e, sort_keys=True))


def _version(dist: str) -> Optional[str]:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def _versions() -> dict:
    return {"python": platform.python_version(), **{d: _version(d) for d in DISTRIBUTIONS}}


def git_state(root: Path, timeout: float = 5.0) -> tuple[Optional[str], Optional[bool]]:
    """(HEAD commit, whether the tree has changes: tracked or untracked, not ignored) of the git
    checkout at ``root``, in one ``git status`` call; (None, None) when ``root`` is no checkout's top
    (an installed package: its site-packages is not the package's checkout, even inside one), git
    is missing, fails or takes over ``timeout`` seconds."""
    return _git_finish(_git_start(root), timeout)


def _git_start(root: Path) -> Optional[subprocess.Popen]:
    if not (Path(root) / ".git").exists():  # a folder, or a file in a worktree
        return None
    env = dict(os.environ, GIT_OPTIONAL_LOCKS="0", LC_ALL="C")  # read-only: never take the index lock
    try:
        return subprocess.Popen(["git", "-C", str(root), "status", "--porcelain=v2", "--branch"],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL,
                                text=True, env=env)
    except OSError:  # no git
        return None


def _git_finish(p: Optional[subprocess.Popen], timeout: float = 5.0) -> tuple[Optional[str], Optional[bool]]:
    if p is None:
        return None, None
    try:
        out, _ = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:  # a huge or network-mounted tree: no commit rather than a slow run
        p.kill()
        p.communicate()
        return None, None
    if p.returncode != 0:
        return None, None
    commit, dirty = None, False
    for line in out.splitlines():
        if line.startswith("# branch.oid "):
            oid = line.split()[-1]
            commit = oid if oid != "(initial)" else None
        elif line and not line.startswith("#"):
            dirty = True
    return commit, (dirty if commit is not None else None)


# --- comparing blocks ---------------------------------------------------------------------------

def _get(block: dict, dotted: str) -> Any:
    node: Any = block
    for part in dotted.split("."):
        if not isinstance(node, dict):
            return None
        node = node.get(part)
    return node


def _text(value: Any) -> str:
    """A field's value as a table shows it."""
    if value is None:
        return "unknown"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, list):
        if value and isinstance(value[0], dict):  # BLAS libraries
            return "; ".join(f"{e.get('library')}: " + " ".join(str(e.get(k)) for k in ("internal_api", "version",
                                                                                          "architecture")
                                                                  if e.get(k) is not None) for e in value)
        return "+".join(str(v) for v in value) or "none"
    return str(value)


def flat(block: Optional[dict]) -> dict[str, str]:
    """The compared fields of a block as text, keyed by their table names (:data:`FIELDS`); {} for None."""
    if not block:
        return {}
    out = {label: _text(_get(block, path)) for path, label in FIELDS}
    if out.get("commit", "unknown") != "unknown":
        out["commit"] = out["commit"][:12]
    return out


def key(block: Optional[dict]) -> str:
    """A short name of a block's compared fields (12 hex digits): equal keys, same machine and versions."""
    return hashlib.sha1(json.dumps(flat(block), sort_keys=True).encode()).hexdigest()[:12]


def summary_line(block: Optional[dict]) -> str:
    """``Intel(R) Xeon(R) Gold 6248 (avx512), numpy 2.4.6, numba 0.68.1, diffuser-lab 0.1.0 @ 6d9df51d536a+dirty``."""
    if not block:
        return "not recorded"
    f = flat(block)
    code = f["diffuser-lab"] + ("" if f["commit"] == "unknown" else f" @ {f['commit']}"
                                + ("+dirty" if f["dirty tree"] == "yes" else ""))
    return f"{f['CPU']} ({f['ISA']}), numpy {f['numpy']}, numba {f['numba']}, diffuser-lab {code}"


def blocks_differ(a: Optional[dict], b: Optional[dict]) -> list[tuple[str, str, str]]:
    """(field, a's value, b's value) of every compared field that differs between two blocks; [] when
    either is missing."""
    if not a or not b:
        return []
    fa, fb = flat(a), flat(b)
    return [(label, fa[label], fb[label]) for _, label in FIELDS if fa[label] != fb[label]]


@dataclass(frozen=True)
class Difference:
    """Fields that split a set of blocks the same way: ``fields`` their names (the first one's
    values are ``counts``: value -> how many blocks)."""

    fields: tuple[str, ...]
    counts: tuple[tuple[str, int], ...]


def differences(blocks: Iterable[Optional[dict]]) -> list[Difference]:
    """What differs among the blocks (missing ones left out), fields that split them alike grouped
    (a CPU model and its ISA, numba target and numpy SIMD go together), in :data:`FIELDS`' order."""
    flats = [flat(b) for b in blocks if b]
    if len(flats) < 2:
        return []
    groups: dict[tuple, list[str]] = {}
    for _, label in FIELDS:
        values = [f[label] for f in flats]
        if len(set(values)) < 2:
            continue
        order: dict[str, int] = {}  # the partition of the blocks by this field, independent of its values
        groups.setdefault(tuple(order.setdefault(v, len(order)) for v in values), []).append(label)
    out = []
    for labels in groups.values():
        counts = Counter(f[labels[0]] for f in flats)
        # most blocks first; a tie in the order the blocks came
        out.append(Difference(tuple(labels), tuple(sorted(counts.items(), key=lambda kv: -kv[1]))))
    return out


def differences_line(blocks: Iterable[Optional[dict]], noun: str = "jobs") -> Optional[str]:
    """One line naming what differs among the blocks and how many per value, e.g. ``mixed machines
    or versions: CPU Intel(R) Xeon(R) Gold 6248 (3 jobs), AMD EPYC 7742 (2 jobs) (with it: vendor,
    ISA, numba target); numpy 2.4.6 (4 jobs), 2.3.1 (1 job)``; None when they agree."""
    diffs = differences(blocks)
    if not diffs:
        return None
    one = noun[:-1] if noun.endswith("s") else noun
    parts = []
    for d in diffs:
        values = ", ".join(f"{v} ({n} {one if n == 1 else noun})" for v, n in d.counts)
        also = f" (with it: {', '.join(d.fields[1:])})" if len(d.fields) > 1 else ""
        parts.append(f"{d.fields[0]} {values}{also}")
    return "mixed machines or versions: " + "; ".join(parts)


__all__ = ["collect", "git_state", "flat", "key", "summary_line", "blocks_differ", "differences",
           "differences_line", "Difference", "FIELDS", "DISTRIBUTIONS"]

if __name__ == "__main__":  # python -m diffuser_lab.backends.provenance: this machine's block
    json.dump(collect(), sys.stdout, indent=2)
    print()
