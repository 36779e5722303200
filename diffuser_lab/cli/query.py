"""``diffuser-lab-query``: relabel a finished features run with words, from its saved features.

    diffuser-lab-query RUN_DIR --queries QUERIES.npz [--threshold T] [--background CLASS] [--mapping CSV] [--out NAME]
    diffuser-lab-query RUN_DIR --encoder module.fn [--names a,b,c] [...]

RUN_DIR is the folder of a run with ``predictions=features`` (``features.npy``, ``summary.json``;
``features_average.npy``, ``features_best_view.npy`` and ``gt_labels.npy`` when it wrote them).
The queries are a ``.npz`` file with ``names`` (Q,) and ``embeddings`` (Q, D) (computed elsewhere,
e.g. with your CLIP), or the names (default: the run's class names) embedded by ``--encoder``, an
importable ``module.fn(list[str]) -> (Q, D)`` (``diffuser_lab.data.embeddings.text_encoder`` is
the simulated network's). A point gets its most similar query's class: the class of the same name
(case-insensitive) or the one ``--mapping`` (lines ``query,class``; ``ignore`` = no class) names;
under ``--threshold`` (a cosine) it gets ``--background`` (a class name; default: unlabeled).

No diffusion, no scene loading: seconds. Prints the usual table (Diffuser and the baselines,
scored against the run's ground truth) and writes ``query_labels.npy`` (Diffuser's labels, (N,)
int16, -1 = unlabeled) and ``query.json`` into RUN_DIR; an earlier query's files are kept (the new
ones get ``_1``, ``_2``... or ``--out NAME``: ``query_labels_NAME.npy``, ``query_NAME.json``).

Exit codes: 0 ok, 1 a bad file (queries, mapping, the run's files), 2 bad arguments.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NoReturn, Optional, Sequence

from diffuser_lab.data.frames import first_line
from diffuser_lab.data.scene import IGNORE
from diffuser_lab.method.queries import Queries, load_encoder
from diffuser_lab.runs.query import FEATURES, output_names, query_run, read_run, table

PROG = "diffuser-lab-query"


class UsageError(Exception):
    """Bad arguments: exit 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, not argparse's usage block
        raise UsageError(message)


def parser() -> argparse.ArgumentParser:
    ap = _Parser(prog=PROG, description=__doc__.split("\n\n")[0].strip(),
                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", metavar="RUN_DIR", help="the folder of a run with predictions=features")
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--queries", metavar="FILE", help=".npz with names (Q,) and embeddings (Q, D)")
    src.add_argument("--encoder", metavar="MODULE.FN", help="a text encoder fn(list[str]) -> (Q, D)")
    ap.add_argument("--names", metavar="A,B,C", help="with --encoder: the query texts (default: the run's classes)")
    ap.add_argument("--threshold", metavar="T", type=float,
                    help="a point whose best cosine is under T gets --background")
    ap.add_argument("--background", metavar="CLASS", help="with --threshold: a class name (default: unlabeled)")
    ap.add_argument("--mapping", metavar="CSV", help="'query,class' lines for queries that are no class name")
    ap.add_argument("--out", metavar="NAME", help="name the files query_labels_NAME.npy, query_NAME.json")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    try:
        return _main(parser().parse_args(argv))
    except UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:
        print(f"{PROG}: error: {first_line(exc)}", file=sys.stderr)
        return 1


def _file(flag: str, path: Optional[str]) -> None:
    if path is not None and not Path(path).is_file():
        raise UsageError(f"{flag} {path}: no such file")


def _main(args: argparse.Namespace) -> int:
    run_dir = Path(args.run_dir)
    if not run_dir.is_dir():
        raise UsageError(f"{run_dir}: no such folder")
    if not (run_dir / FEATURES).is_file():
        raise UsageError(f"{run_dir}: no {FEATURES}, expected the folder of a run with predictions=features")
    if args.queries is None and args.encoder is None:
        raise UsageError("give --queries FILE or --encoder MODULE.FN")
    if args.names is not None and args.encoder is None:
        raise UsageError("--names goes with --encoder (a query file has its names)")
    if args.threshold is not None and not -1.0 <= args.threshold <= 1.0:
        raise UsageError(f"--threshold {args.threshold:g}: expected a cosine in [-1, 1]")
    if args.background is not None and args.threshold is None:
        raise UsageError("--background goes with --threshold")
    _file("--queries", args.queries)
    _file("--mapping", args.mapping)
    try:
        output_names(run_dir, args.out)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    run = read_run(run_dir)
    background = IGNORE
    if args.background is not None:
        index = {n.lower(): i for i, n in enumerate(run.class_names)}
        if args.background.strip().lower() not in index:
            raise UsageError(f"--background {args.background}: not a class of the run ({', '.join(run.class_names)})")
        background = index[args.background.strip().lower()]
    if args.queries is not None:
        queries = Queries.from_file(args.queries, dim=run.dim)
    else:
        names = run.class_names if args.names is None else [n.strip() for n in args.names.split(",") if n.strip()]
        if not names:
            raise UsageError(f"--names {args.names!r}: expected comma-separated query texts")
        try:
            load_encoder(args.encoder)  # a target that is no function is the command line's fault (2)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        queries = Queries.from_encoder(names, args.encoder)  # what it returns is like a file's content (1)
    res = query_run(run, queries, threshold=args.threshold, background=background, mapping=args.mapping,
                    out=args.out)
    print(table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
