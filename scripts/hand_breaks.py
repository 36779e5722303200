"""Does the quick loop catch a broken equation? (issue 61 item 4)

Each named hand-break is a one-line edit of the method's code (an equation, the early stop, a tie
rule, a tolerance, an update; its numba kernel and its numpy twin apart). For each, the repository's
tracked and untracked-but-not-ignored files are copied to a temporary folder, the edit applied, and
the quick loop run there:

    python -m pytest -m "not slow" -x -q

with the copy first on ``PYTHONPATH`` (the checkout's editable install would otherwise import the
unbroken package). A copy whose edit is Python code takes the checkout's numba cache with it (the
kernels are the same); one whose edit is in ``diffuser_lab/backends/numba/`` starts with an empty
cache, since numba's cache does not see a change in a kernel another file's kernel calls. The report
says, per break, whether the quick loop failed (caught), the first tests that failed and the time.

    python scripts/hand_breaks.py                    # every break, then a table (markdown)
    python scripts/hand_breaks.py --only eq16-tie-numba,depth-tol-numpy
    python scripts/hand_breaks.py --baseline         # the copy unbroken: the quick loop must pass
    python scripts/hand_breaks.py --list

Not a test: the suite only checks that every break still applies to the code
(``tests/test_hand_breaks.py``). Results: docs/results/testing.md.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Break:
    name: str
    what: str  # the equation or rule, and which twin
    path: str  # relative to the repository
    old: str  # occurs exactly once in the file
    new: str


BREAKS = [
    Break("eq4-weight-numpy", "Eq. 4's distance term 1/(2 sigma_d^2) -> 1/sigma_d^2 (numpy twin)",
          "diffuser_lab/backends/knn.py", "expo = d2 * (-0.5 / sigma_d**2)", "expo = d2 * (-1.0 / sigma_d**2)"),
    Break("eq4-weight-numba", "Eq. 4's |x_i - x_j|^2 without its z term (numba kernel)",
          "diffuser_lab/backends/numba/weights.py", "ex[e0 + s] = -(dx * dx + dy * dy + dz * dz) * a_d - t * a_s",
          "ex[e0 + s] = -(dx * dx + dy * dy) * a_d - t * a_s"),
    Break("early-stop-python", "the early stop at 10 tol (the backends' step loop)",
          "diffuser_lab/backends/base.py", "            if residual(change, top) <= self.tol:",
          "            if residual(change, top) <= 10 * self.tol:"),
    Break("early-stop-numba", "the early stop at 10 tol (the compiled steps' rule)",
          "diffuser_lab/backends/numba/_sync.py", "return (np.float64(gch) / np.float64(gtp) if gtp > 0 else 0.0) <= tol",
          "return (np.float64(gch) / np.float64(gtp) if gtp > 0 else 0.0) <= 10 * tol"),
    Break("eq16-tie-numpy", "Eq. 16's ties to the highest class (numpy argmax)",
          "diffuser_lab/method/diffusion.py", "lab = np.argmax(Z, axis=1).astype(np.int16)",
          "lab = (Z.shape[1] - 1 - np.argmax(Z[:, ::-1], axis=1)).astype(np.int16)"),
    Break("eq16-tie-numba", "Eq. 16's ties to the later class block (numba argmax)",
          "diffuser_lab/backends/numba/jacobi.py", "                if v > best[i]:", "                if v >= best[i]:"),
    Break("depth-tol-numpy", "the depth check's tolerance doubled (numpy projection)",
          "diffuser_lab/data/geometry.py", "ok = (d > 0) & (np.abs(z[idx] - d) <= depth_tol)",
          "ok = (d > 0) & (np.abs(z[idx] - d) <= 2 * depth_tol)"),
    Break("depth-tol-numba", "the depth check's tolerance doubled (numba votes)",
          "diffuser_lab/backends/numba/evidence.py", "if not (d > 0 and abs(zc - d) <= tol):",
          "if not (d > 0 and abs(zc - d) <= 2 * tol):"),
    Break("bayes-sum-numpy", "the Bayesian sum of likelihoods -> their maximum (numpy evidence)",
          "diffuser_lab/method/evidence.py", "                ev.mass[i[good]] += vec",
          "                ev.mass[i[good]] = np.maximum(ev.mass[i[good]], vec)"),
    Break("bayes-votes-numba", "a vote counted once per point, not once per view (numba votes)",
          "diffuser_lab/backends/numba/evidence.py", "            mass[i, lab] += 1.0", "            mass[i, lab] = 1.0"),
    Break("bayes-online", "the online Bayesian labels not updated by a frame's evidence",
          "diffuser_lab/method/online.py",
          "            self._bayes[seen_base] = labels_from_scores(self.ev.baseline.mass[seen_base])",
          "            pass"),
    Break("lift-median", "VALA's Weiszfeld weight w / d -> w d (median rule)",
          "diffuser_lab/method/lifters.py", "c = w / np.maximum(d, WEISZFELD_EPS)", "c = w * np.maximum(d, WEISZFELD_EPS)"),
    Break("lift-weighted", "the weighted average without its weights (weighted rule)",
          "diffuser_lab/method/lifters.py", "self.sum[idx] += w[:, None] * x", "self.sum[idx] += x"),
    Break("online-discount", "the online discount gamma = 2^(-1/T) instead of 2^(-2/T)",
          "diffuser_lab/method/online.py", "return float(2.0 ** (-2.0 / max(int(horizon), 1)))",
          "return float(2.0 ** (-1.0 / max(int(horizon), 1)))"),
    Break("online-steps", "a frame's warm-started steps: one instead of online.steps",
          "diffuser_lab/method/online.py", "out = self.system.steps(self.steps, region)",
          "out = self.system.steps(1, region)"),
    Break("online-map-rows", "the growing map's old rows keep their neighbours when new points come",
          "diffuser_lab/method/growing.py", "            self._rows.update(self._arrays(), old_rows)",
          "            pass"),
]
"""The named hand-breaks, each a one-line edit."""


def apply(root: Path, b: Break) -> None:
    """``b``'s edit, in the tree at ``root``; its ``old`` text must occur exactly once."""
    p = root / b.path
    text = p.read_text()
    if text.count(b.old) != 1:
        raise ValueError(f"{b.name}: {b.path} holds {text.count(b.old)} copies of {b.old!r}, expected 1")
    p.write_text(text.replace(b.old, b.new))


def copy_tree(dst: Path, warm: bool) -> None:
    """The checkout's tracked and untracked-not-ignored files to ``dst`` (modification times kept);
    ``warm``: the package's __pycache__ folders too (the numba cache); ``../shared`` linked beside it."""
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, check=True).stdout.decode().split("\0")
    for f in filter(None, files):
        src = ROOT / f
        if src.is_file():
            (dst / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / f)
    if warm:
        for cache in (ROOT / "diffuser_lab").rglob("__pycache__"):
            shutil.copytree(cache, dst / cache.relative_to(ROOT), dirs_exist_ok=True)
    shared = ROOT.parent / "shared"
    if shared.exists() and not (dst.parent / "shared").exists():
        (dst.parent / "shared").symlink_to(shared)


def quick_loop(root: Path, extra: list[str]) -> dict:
    """The quick loop in ``root``: its exit status, seconds, summary line and the tests that failed."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    env.pop("PYTEST_XDIST_WORKER", None)
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "pytest", "-m", "not slow", "-x", "-q", "-p", "no:randomly", *extra],
                       cwd=root, env=env, capture_output=True, text=True)
    out = p.stdout + p.stderr
    failed = sorted(set(re.findall(r"^(?:FAILED|ERROR) (\S+)", out, re.M)))
    summary = next((ln.strip("= ") for ln in reversed(out.splitlines()) if re.search(r"\d+ (passed|failed)", ln)), "")
    return {"rc": p.returncode, "seconds": time.monotonic() - t0, "failed": failed, "summary": summary,
            "tail": out[-3000:]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", default="", help="comma-separated break names")
    ap.add_argument("--baseline", action="store_true", help="run the unbroken copy (warm) only")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--keep", action="store_true", help="keep the copies (printed)")
    ap.add_argument("pytest_args", nargs="*", help="more pytest arguments (after --)")
    args = ap.parse_args(argv)
    if args.list:
        for b in BREAKS:
            print(f"{b.name:20s} {b.path}: {b.what}")
        return 0
    chosen = [b for b in BREAKS if not args.only or b.name in args.only.split(",")]
    if args.only and len(chosen) != len(args.only.split(",")):
        ap.error(f"--only: unknown names in {args.only!r} (--list)")
    jobs = [None] if args.baseline else chosen
    rows, missed = [], []
    for b in jobs:  # loop over breaks (each a copy and a quick loop, minutes)
        tmp = Path(tempfile.mkdtemp(prefix=f"hand-break-{b.name if b else 'baseline'}-"))
        root = tmp / "repo"
        cold = b is not None and b.path.startswith("diffuser_lab/backends/numba/")
        copy_tree(root, warm=not cold)
        if b is not None:
            apply(root, b)
        r = quick_loop(root, args.pytest_args)
        caught = r["rc"] != 0 if b else r["rc"] == 0
        name = b.name if b else "baseline (no break)"
        tests = ", ".join(f"`{t}`" for t in r["failed"][:3]) or "-"
        what = (b.what if b else "the copy as it is").replace("|", "\\|")  # a markdown cell
        rows.append(f"| {name} | {what} | {'caught' if caught and b else 'passes' if caught else 'MISSED' if b else 'FAILS'} "
                    f"| {tests} | {r['seconds']:.0f} s{', cold cache' if cold else ''} |")
        print(rows[-1], flush=True)
        if not caught:
            missed.append(name)
            print(r["tail"], file=sys.stderr)
        if args.keep:
            print(f"  kept: {root}", flush=True)
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    print("\n| break | what | quick loop | first failing tests | time |\n| --- | --- | --- | --- | --- |")
    print("\n".join(rows))
    if missed:
        print(f"\nnot caught: {', '.join(missed)}", file=sys.stderr)
    return 1 if missed else 0


if __name__ == "__main__":
    raise SystemExit(main())
