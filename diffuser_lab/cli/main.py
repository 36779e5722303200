"""`diffuser-lab`: the Hydra command line. One run = one folder under logs/.

Start-up order: the command line is composed and validated first (unknown keys, wrong
types, values out of range -> one line naming the key, exit 2), then Hydra runs the job.
"""
from __future__ import annotations

import logging
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Optional, Sequence

from diffuser_lab.backends import numba as nb
from diffuser_lab.config import ConfigError, RecordMode, SolverBackend, check_moved, moved_key, register, to_object
from diffuser_lab.data import inputs
from diffuser_lab.recording import make_hooks, record_result
from diffuser_lab.recording.heap import retain_freed_memory
from diffuser_lab.runs import launchers, memory, report
from diffuser_lab.runs.pipeline import reuse_scenes
from diffuser_lab.data.frames import read_ahead
from diffuser_lab.runs.protocols import PROTOCOLS
from diffuser_lab.runs.resolve import resolve
from diffuser_lab.progress import say
from diffuser_lab.runs.sweep import job_line, job_tag, print_table

log = logging.getLogger("diffuser_lab")
PROG = "diffuser-lab"


def config_dir() -> str:
    """The Hydra config folder: the wheel's ``diffuser_lab/conf`` when installed, else the
    checkout's top-level ``conf/``."""
    here = Path(__file__).resolve().parent.parent  # the package folder
    for cand in (here / "conf", here.parent / "conf"):
        if (cand / "config.yaml").is_file():
            return str(cand)
    raise FileNotFoundError(f"no Hydra config folder (config.yaml) in {here / 'conf'} or {here.parent / 'conf'}")


def one_line(exc: BaseException) -> str:
    """A config or input error as one line, naming the key when OmegaConf/Hydra know it."""
    chain = []
    e: Optional[BaseException] = exc
    while e is not None and len(chain) < 8:
        chain.append(e)
        e = e.__cause__ or e.__context__
    # OmegaConf's formatted error (the one with "full_key:") names the key and the problem
    for e in chain:
        lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
        keys = [ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("full_key:")]
        if keys and moved_key(keys[0]):  # a YAML file spelling a scene source's key the old way
            return f"{keys[0]} is now {moved_key(keys[0])}: every scene source's keys are scene.options.KEY"
        if keys and lines and "missing mandatory value" in lines[0].lower():  # a MISSING key of the schema
            return f"{keys[0]} is required (pass {keys[0]}=...)"
        if keys and lines:
            return lines[0] if keys[0] in lines[0] else f"{keys[0]}: {lines[0]}"
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    if not lines:
        return type(exc).__name__
    msg = lines[0]
    if any(ln.startswith("Available options") for ln in lines):  # Hydra: unknown group option
        i = next(i for i, ln in enumerate(lines) if ln.startswith("Available options"))
        opts = [ln for ln in lines[i + 1 :] if not ln.startswith(("Config search path", "provider="))]
        msg += f" (available: {', '.join(opts)})"
    return msg


def _one(text: str, limit: int = 300) -> str:
    """``text`` on one line, at most ``limit`` characters."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _verbose() -> bool:
    return os.environ.get("HYDRA_FULL_ERROR") == "1"


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> str:
    return f"{PROG}: warning: {message}\n"


def _prevalidate(argv: list[str]) -> None:
    """Compose the single-run config the way Hydra will and check it; exit 2 with one line."""
    if any(a.startswith("-") for a in argv):  # --help, --cfg, -m/--multirun: leave them to Hydra
        return
    for a in argv:  # an explicit run folder that already holds a run is never reused
        if a.startswith("hydra.run.dir="):
            d = Path(a.split("=", 1)[1])
            if d.is_dir() and any(d.iterdir()):
                print(f"{PROG}: error: hydra.run.dir={d} is not empty; earlier runs are never overwritten",
                      file=sys.stderr)
                sys.exit(2)
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    try:
        with initialize_config_dir(config_dir=config_dir(), version_base="1.3", job_name="prevalidate"):
            cfg = compose(config_name="config", overrides=argv, return_hydra_config=False)
            resolve(to_object(cfg), PROTOCOLS)
    except Exception as exc:  # noqa: BLE001 - every start-up failure becomes one line
        if _verbose():
            raise
        print(f"{PROG}: error: {one_line(exc)}", file=sys.stderr)
        sys.exit(2)
    finally:
        GlobalHydra.instance().clear()


class JobFailed(Exception):
    """A run that failed: ``summary`` its summary.json content (``status: failed``, the error, the
    inputs read so far), ``cause`` the exception."""

    def __init__(self, cause: BaseException, summary: dict):
        super().__init__(str(cause))
        self.cause, self.summary = cause, summary


def execute(cfg: Any, run_dir: Path, overrides: Sequence[str], *, multirun: bool = False,
            kernels: Optional[str] = None) -> tuple[Any, Any, dict]:
    """One run into ``run_dir`` (a new, empty folder): resolve the composed config ``cfg`` (a
    DictConfig of the schema), run its protocol (the protocols' registry entry) with its records,
    write its files and summary.json with what it read (the inputs recorded while it ran:
    :mod:`diffuser_lab.data.inputs`) and wrote (their hashes), and hand those to the records before
    they close. Returns (the resolved config, the protocol's result, summary.json's content); raises
    :class:`JobFailed` (summary.json says ``failed``) when the run fails. The ``diffuser-lab``
    command's job (:func:`_task`) and ``diffuser-lab-verify``'s re-run. ``kernels``: ``numba`` or
    ``numpy`` to take that path whatever numba's cache holds (a re-run takes its run's, summary.json
    ``kernels``); None: the numpy/scipy path while the cache is cold (:func:`_defer_compile`)."""
    summary: Optional[report.SummaryFile] = None
    conf: Any = None
    read: Optional[inputs.Collector] = None
    show = warnings.showwarning

    def keep(message, category, filename, lineno, file=None, line=None):  # print and record
        if summary is not None:
            summary.warn(str(message))
        show(message, category, filename, lineno, file, line)

    warnings.showwarning = keep
    deferred = pinned = False
    memory.reset_peak()  # summary.json's memory: this job's peak, also in a sweep's shared process
    reuse_scenes(multirun)  # a sweep's jobs in this process load each scene once
    try:
        with inputs.collecting() as read:  # every file the readers read from here on, hashed
            summary = report.SummaryFile(run_dir, overrides)
            conf = resolve(to_object(cfg), PROTOCOLS)
            if kernels == "numpy" and nb.available():
                nb.defer_compile()
                pinned = True
            elif kernels is None:
                deferred = _defer_compile(conf)
            # which kernels ran (numba's or their numpy/scipy twins: figures agree to float rounding only)
            # split: validation / test of a tuning protocol (docs/sweeps.md), null otherwise; reports keep them apart
            summary.update(method=conf.method.name, kernels="numba" if nb.available() else "numpy",
                           split=conf.split.value if conf.split is not None else None)
            protocol = PROTOCOLS[conf.protocol.name]
            hooks = _record_hooks(conf, run_dir, overrides) if protocol.records else None
            try:
                with read_ahead(conf.scene.read_ahead):  # every protocol's frame loops
                    result = protocol.run(conf, hooks=hooks, **({"run_dir": run_dir} if protocol.run_dir else {}))
            except BaseException:
                if hooks is not None:
                    hooks.close()
                raise
        try:  # the records close once they have the run's inputs and outputs (killed before: still readable)
            done = protocol.finish(result, conf, run_dir, summary, {})
            sealed = summary.seal(conf, read)
            if hooks is not None:
                hooks.on_provenance({"provenance": summary.data.get("provenance"), **sealed})
        finally:
            if hooks is not None:
                hooks.close()
        if hooks is not None:
            records = hooks.files()
        elif protocol.result_records:  # written by this process from the result (a tiled run's)
            t_rec = time.perf_counter()
            records = record_result(conf, run_dir, result, overrides=list(overrides),
                                    provenance={"provenance": summary.data.get("provenance"), **sealed})
            if records:
                summary.data.setdefault("timings_s", {})["records"] = round(time.perf_counter() - t_rec, 4)
                if isinstance(getattr(result, "timings_s", None), dict):  # the table's line
                    result.timings_s["records"] = time.perf_counter() - t_rec
        else:
            records = {}
        summary.update(records=records, memory=memory.snapshot())
        return conf, result, summary.data
    except Exception as exc:  # noqa: BLE001 - recorded in summary.json, then raised
        error = f"{type(exc).__name__}: {one_line(exc)}"
        if summary is None:
            raise JobFailed(exc, {"status": "failed", "error": error}) from exc
        try:  # what it read until then: a bad input file is among them
            summary.seal(conf, read)
        except Exception:  # noqa: BLE001 - the error is what is reported
            pass
        raise JobFailed(exc, summary.failed(error) or {"status": "failed", "error": error}) from exc
    finally:
        warnings.showwarning = show
        if pinned:  # this process's next run decides again
            nb.undefer()
        if deferred:  # after the run: the compile does not compete with it for the CPUs
            nb.compile_in_background()


def _task(cfg: Any) -> Optional[float]:
    """The Hydra job: :func:`execute` into Hydra's run folder, then the table (a sweep: a line)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    t_start = time.perf_counter()
    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    if multirun and "BasicLauncher" not in str(hc.launcher.get("_target_", "")):
        # jobs run side by side: say which one starts (the basic launcher's "#i :" line does)
        say(f"{job_tag(hc.job.num)} started {' '.join(hc.overrides.task)}")
        if hc.launcher.get("cpus_per_task"):  # submitit: the job's share of the CPUs
            nb.limit_threads(int(hc.launcher.cpus_per_task))
    try:
        conf, result, done = execute(cfg, run_dir, list(hc.overrides.task), multirun=multirun)
    except JobFailed as failed:
        exc = failed.cause
        if multirun:
            say(job_line(hc.job.num, run_dir, failed.summary))
        if multirun or _verbose():
            raise exc  # Hydra marks this job failed and goes on with the others
        print(f"{PROG}: error: {one_line(exc)}", file=sys.stderr)
        sys.exit(1)
    if multirun:  # one line per job; the sweep's table comes at the end (sweep.print_table)
        say(job_line(hc.job.num, run_dir, done, time.perf_counter() - t_start))
    elif not conf.output.quiet:
        print(PROTOCOLS[conf.protocol.name].table(result, run_dir))
    failed_records = (done.get("records") or {}).get("errors")
    if failed_records and not multirun:  # the labels are written: now say the records are not, in one line
        names = {"rerun": "run.rrd", "mcap": "run.mcap"}
        which = "; ".join(f"{names.get(k, k)}: {why}" for k, why in sorted(failed_records.items()))
        print(f"{PROG}: error: {run_dir}: a record could not be written ({_one(which)}); the labels and "
              f"summary.json are written", file=sys.stderr)
        sys.exit(1)
    return (done.get("metrics") or {}).get("miou")


def _record_hooks(conf: Any, run_dir: Path, overrides: Sequence[str]):
    """The run's recorders (in a recording process), or None for record=off."""
    if conf.record.mode == RecordMode.off:
        return None
    retain_freed_memory(conf.record.retain_heap_mb)  # process-wide: the command line's choice
    return make_hooks(conf, run_dir, overrides=list(overrides), process=True)


def _defer_compile(conf: Any) -> bool:
    """On an empty numba cache, run this job on the numpy/scipy path (same labels) and say so in
    one line, rather than compile for ~25 s first; ``DIFFUSER_LAB_NUMBA=1`` or an explicit
    ``solver.backend`` compiles in the foreground."""
    if not nb.available() or nb.forced() or conf.solver.backend != SolverBackend.auto:
        return False
    if not nb.cold():
        return False
    nb.defer_compile()
    print(f"{PROG}: numba kernels are not compiled yet: this run takes the numpy/scipy path; they compile "
          "in the background when it ends (~25 s, once; DIFFUSER_LAB_NUMBA=1 compiles them first)",
          file=sys.stderr, flush=True)
    return True


def main() -> None:
    """Console entry point ``diffuser-lab``."""
    import hydra

    register()
    launchers.register()
    if "--verbose" in sys.argv:  # full tracebacks, as HYDRA_FULL_ERROR=1
        sys.argv.remove("--verbose")
        os.environ["HYDRA_FULL_ERROR"] = "1"
    warnings.formatwarning = _one_line_warning
    # Rerun's own (Rust) log lines would repeat a record's failure over several lines: this
    # command reports it in one (set RUST_LOG to see them)
    os.environ.setdefault("RUST_LOG", "off")
    try:  # before Hydra, in every mode (-m too): a key spelled the old way names its new spelling
        for a in sys.argv[1:]:
            check_moved(a)
    except ConfigError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        sys.exit(2)
    _prevalidate(sys.argv[1:])
    app = hydra.main(config_path=config_dir(), config_name="config", version_base="1.3")(_task)
    try:
        app()
    finally:  # also when a job failed: Hydra raises after the batch, the table still shows
        print_table()


if __name__ == "__main__":
    main()
