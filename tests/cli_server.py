"""A fork server for the tests' ``diffuser-lab`` commands (:func:`conftest.run_cli`).

A command line run as ``python -m diffuser_lab ARGS`` spends ~1.3 s importing the package (numba,
scipy, Hydra, ...) and ~0.3 s tearing the interpreter down before and after the run; the suite runs
a hundred-odd of them. This server imports ``diffuser_lab.cli.main`` once and forks a child per
command: the child takes the command's working directory, environment, ``sys.argv`` and
``sys.path[0]`` (what ``python -m`` sets), reads stdin from /dev/null, writes stdout and stderr to
the files it is given and runs the package's ``__main__`` as ``python -m`` does; its exit status is
the command's. The run itself (Hydra, the config, the numba kernels from the cache, the records)
is the same code in a fresh process; only imports that already happened are not repeated, so a
command whose environment differs from the server's (variables read at import time, such as
``NUMBA_*``) is run in a fresh interpreter by the caller instead. The README's commands are always
run as written (tests/test_readme.py), never here.

Protocol (stdin/stdout of the server, one JSON line each): request ``{"args", "cwd", "env", "out",
"err"}``, replies ``{"pid": child}`` when it started, then ``{"status": exit status}``.
"""
from __future__ import annotations

import atexit
import json
import os
import runpy
import sys


def _child(req: dict) -> int:
    """The command in this (forked) process; returns its exit status."""
    os.chdir(req["cwd"])
    os.environ.clear()
    os.environ.update(req["env"])
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    for fd, path in ((1, req["out"]), (2, req["err"])):
        f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(f, fd)
        os.close(f)
    sys.stdin = open(0, closefd=False)
    sys.stdout = open(1, "w", buffering=1, closefd=False)  # a file: block buffered as in a pipe
    sys.stderr = open(2, "w", buffering=1, closefd=False)
    sys.path[0] = req["cwd"]  # python -m puts the working directory first
    sys.argv = [os.path.join(os.path.dirname(__import__("diffuser_lab").__file__), "__main__.py"), *req["args"]]
    code = 0
    try:
        runpy.run_module("diffuser_lab", run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        c = exc.code
        code = c if isinstance(c, int) else (0 if c is None else 1)
        if c is not None and not isinstance(c, int):
            print(c, file=sys.stderr)
    except BaseException:  # noqa: BLE001 - as the interpreter: the traceback, status 1
        import traceback

        traceback.print_exc()
        code = 1
    try:
        atexit._run_exitfuncs()  # what the interpreter runs at exit (logging's flush, ...)
    finally:
        for s in (sys.stdout, sys.stderr):
            try:
                s.flush()
            except Exception:  # noqa: BLE001
                pass
    return code


def load_kernels() -> int:
    """The imported package's numba kernels loaded from numba's cache, as a command's first calls
    would (~0.4 s for ~50 overloads), without calling any: the parallel ones (``parallel=True``)
    are left to the commands, since loading one starts numba's worker threads, which a fork does
    not copy. Returns the overloads loaded."""
    from numba.core.dispatcher import Dispatcher

    seen, n = set(), 0
    for name, mod in list(sys.modules.items()):
        if not name.startswith("diffuser_lab") or mod is None:
            continue
        for d in list(vars(mod).values()):
            if not isinstance(d, Dispatcher) or id(d) in seen or d.targetoptions.get("parallel"):
                continue
            seen.add(id(d))
            index = getattr(getattr(d, "_cache", None), "_cache_file", None)
            if index is None:
                continue
            magic = d.targetctx.codegen().magic_tuple()
            for key in index._load_index():  # {} where the source changed since the cache was written
                if key[1] == magic:  # compiled for this CPU (the cache holds other machines' too)
                    try:
                        d.compile(key[0])
                        n += 1
                    except Exception:  # noqa: BLE001 - the command loads (or compiles) it itself
                        pass
    return n


def serve() -> None:
    import diffuser_lab.cli.main  # noqa: F401 - the imports every command makes

    load_kernels()
    out = sys.stdout
    for line in sys.stdin:
        req = json.loads(line)
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                code = _child(req)
            finally:
                os._exit(code)
        out.write(json.dumps({"pid": pid}) + "\n")
        out.flush()
        _, status = os.waitpid(pid, 0)
        out.write(json.dumps({"status": os.waitstatus_to_exitcode(status)}) + "\n")
        out.flush()


if __name__ == "__main__":
    serve()
