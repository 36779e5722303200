"""What a run read: every input file's size and sha256, recorded by the readers as they read it.

The one home of input hashing. The readers (:mod:`.images`, :mod:`.arrays`, :mod:`.clouds`, :mod:`.meshes`,
:mod:`.poses`, :mod:`.intrinsics`, :mod:`.prediction_files`, :mod:`.embeddings`, :mod:`.networks`,
:mod:`.taxonomy`, :mod:`.mapping`, a source's index files) call :func:`record` (or :func:`read_bytes`,
which reads and records) with the file and its role; nothing else hashes an input. A recorder is
active only inside :func:`collecting` (the command line wraps each run in one; a tile wraps its own
run, in this process or a Ray worker): outside it :func:`record` returns at once, so a library
caller pays nothing. Frames are read ahead on threads (:mod:`.frames`): :func:`record` is
thread-safe (stat and hash outside the lock, the bookkeeping inside).

**Hashed while read.** A reader that has the file's bytes (an image, a mesh, a pose) passes them:
no second read. Others (LAS, a bag, an ONNX file) are read once more for the hash, from the page
cache.

**The hash cache** (:class:`HashCache`): sha256 by (absolute path, size, mtime_ns, inode), read a
folder at a time (the first file of a folder a run reads brings its folder's rows), in an SQLite file ``~/.cache/diffuser-lab/input-hashes.sqlite`` (``$XDG_CACHE_HOME`` when set;
``DIFFUSER_LAB_HASH_CACHE=PATH`` elsewhere, ``=off`` none). In the user's cache dir, not a run's
folder or a checkout's ``logs/``: the keys are absolute paths of data every checkout and sweep of
the user reads. SQLite's locks (WAL, a 30 s busy timeout) let the jobs of a sweep on the joblib or
Ray launchers read and add at once; each process opens its own connection (a forked one reopens).
A file modified less than :data:`RACY_S` seconds before it was hashed is not cached (its mtime
could repeat after an edit within the file system's clock tick: git's "racily clean" rule). A
cache that cannot be opened or written is switched off for the process; hashing goes on.

**What a run reports** (:func:`block`, summary.json ``inputs``): the roles of
:data:`MANIFEST_ROLES` (frames, predictions, feature maps: thousands of files) as one manifest
each, ``{"count", "bytes", "sha256"}`` where sha256 = :func:`manifest` of the files' hashes; the
others (mesh, cloud, intrinsics, network, queries, taxonomy, mapping, capture index files) file by
file, ``{"role", "path", "size", "sha256"}`` (a listed role of over :data:`LISTED_MAX` files
becomes a manifest too). Every file, one line each, goes to the run folder's ``inputs.tsv``
(:func:`write_list`): what ``diffuser-lab-verify`` names a changed file from.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import sqlite3
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Optional, Union

__all__ = ["Entry", "Collector", "HashCache", "record", "read_bytes", "collecting", "merge", "active",
           "sha256_bytes", "sha256_file", "manifest", "block", "write_list", "read_list", "compare_lists",
           "cache_path", "MANIFEST_ROLES", "LIST_NAME"]

MANIFEST_ROLES = ("frames", "predictions", "features")
"""Roles of many files (one per frame): one manifest each in summary.json, never a list."""
LISTED_MAX = 8
"""A listed role (mesh, intrinsics, ...) of more files than this is a manifest too (per-frame intrinsics)."""
RACY_S = 2.0
"""A file modified this recently when hashed is not cached (an edit within the mtime's tick)."""
LIST_NAME = "inputs.tsv"
"""The run folder's file of every input, one line each (:func:`write_list`)."""
BLOCK = 1 << 20

PathLike = Union[str, os.PathLike]


@dataclass(frozen=True)
class Entry:
    """One file a run read: ``role`` (frames, predictions, mesh, ...), absolute ``path``, ``size``
    in bytes and the content's ``sha256`` (64 hex digits)."""

    role: str
    path: str
    size: int
    sha256: str


def sha256_bytes(data) -> str:
    """sha256 of bytes (or a buffer), 64 hex digits (hashlib releases the GIL: threads hash side by side)."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: PathLike) -> tuple[int, str]:
    """(bytes read, sha256) of a file, read 1 MiB at a time."""
    h, n = hashlib.sha256(), 0
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(BLOCK), b""):
            h.update(chunk)
            n += len(chunk)
    return n, h.hexdigest()


def manifest(hashes: Iterable[str]) -> str:
    """One hash over many files: sha256 of ``"<count>\\n"`` and the sorted hex hashes, one a line.
    Independent of paths and order: a moved folder keeps its manifest; an edited file changes it."""
    hs = sorted(hashes)
    return sha256_bytes((f"{len(hs)}\n" + "".join(h + "\n" for h in hs)).encode())


# --------------------------------------------------------------------------- the cache

def cache_path() -> Optional[Path]:
    """The hash cache's file (module doc), None when ``DIFFUSER_LAB_HASH_CACHE=off``."""
    env = os.environ.get("DIFFUSER_LAB_HASH_CACHE")
    if env:
        return None if env.lower() in ("off", "0", "none") else Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "diffuser-lab" / "input-hashes.sqlite"


Key = tuple[str, int, int, int]  # (absolute path, size, mtime_ns, inode)


class HashCache:
    """sha256 by (path, size, mtime_ns, inode) in an SQLite file (module doc): one row per path (its
    latest hash: a file edited in place replaces its row), read a folder at a time (:meth:`folder`:
    one query answers every frame of a folder), new rows written in batches (:meth:`flush`: at
    :data:`FLUSH_EVERY` and when a run's collecting ends). Not thread-safe by itself: :func:`record`
    calls it under its lock."""

    FLUSH_EVERY = 512

    def __init__(self, path: Optional[Path]):
        self.path = path
        self.error: Optional[str] = None if path is not None else "off (DIFFUSER_LAB_HASH_CACHE=off)"
        self._db: Optional[sqlite3.Connection] = None
        self._pid = 0
        self._pending: list[tuple] = []

    @staticmethod
    def _ino(ino: int) -> int:
        return ino if ino < 2**63 else ino - 2**64  # SQLite's integers are signed 64-bit

    def _conn(self) -> Optional[sqlite3.Connection]:
        if self.error is not None:
            return None
        if self._db is not None and self._pid == os.getpid():
            return self._db
        self._db, self._pending = None, []  # a forked child: the parent's connection is not ours
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            db = sqlite3.connect(str(self.path), timeout=30, check_same_thread=False, isolation_level=None)
            with contextlib.suppress(sqlite3.Error):  # a file system without shared memory: rollback journal
                db.execute("PRAGMA journal_mode=WAL")
            db.execute("CREATE TABLE IF NOT EXISTS files (dir TEXT NOT NULL, name TEXT NOT NULL, "
                       "size INTEGER NOT NULL, mtime_ns INTEGER NOT NULL, inode INTEGER NOT NULL, "
                       "sha256 TEXT NOT NULL, PRIMARY KEY (dir, name)) WITHOUT ROWID")
        except (sqlite3.Error, OSError) as exc:
            self._off(exc)
            return None
        self._db, self._pid = db, os.getpid()
        return db

    def _off(self, exc: BaseException) -> None:
        self.error = f"off ({type(exc).__name__}: {exc})"
        self._db, self._pending = None, []

    def folder(self, folder: str) -> dict[Key, str]:
        """{key: sha256} of every file of ``folder`` (absolute) in the cache."""
        db = self._conn()
        if db is None:
            return {}
        try:
            rows = db.execute("SELECT name, size, mtime_ns, inode, sha256 FROM files WHERE dir=?", (folder,)).fetchall()
        except sqlite3.Error as exc:
            self._off(exc)
            return {}
        return {(os.path.join(folder, n), size, mtime, ino if ino >= 0 else ino + 2**64): sha
                for n, size, mtime, ino, sha in rows}

    def put(self, key: Key, sha: str) -> None:
        if self.error is None:
            p, size, mtime, ino = key
            self._pending.append((*os.path.split(p), size, mtime, self._ino(ino), sha))
            if len(self._pending) >= self.FLUSH_EVERY:
                self.flush()

    def flush(self) -> None:
        """Write the new rows in one transaction."""
        db = self._conn() if self._pending else None
        if db is None:
            return
        rows, self._pending = self._pending, []
        try:
            db.execute("BEGIN IMMEDIATE")
            db.executemany("INSERT OR REPLACE INTO files VALUES (?, ?, ?, ?, ?, ?)", rows)
            db.execute("COMMIT")
        except sqlite3.Error as exc:
            with contextlib.suppress(sqlite3.Error):
                db.execute("ROLLBACK")
            self._off(exc)

    def describe(self) -> str:
        return self.error or str(self.path)


# --------------------------------------------------------------------------- the recorder

@dataclass
class Collector:
    """The files read while it was active (:func:`collecting`), by (role, path), and what hashing
    them cost: ``hashed`` files and ``bytes_hashed`` (cache misses), ``cached`` (hits), ``seconds``
    spent in :func:`record` (stat, cache, hash) summed over the threads that read."""

    entries: dict = field(default_factory=dict)
    hashed: int = 0
    bytes_hashed: int = 0
    cached: int = 0
    seconds: float = 0.0

    def add(self, e: Entry) -> None:
        self.entries[(e.role, e.path)] = e

    def rows(self) -> list[Entry]:
        """The entries sorted by role and path."""
        return [self.entries[k] for k in sorted(self.entries)]


_LOCK = threading.Lock()
_ACTIVE: list[Collector] = []
_MEMO: dict[Key, str] = {}  # this run's hashes by key: the cache's rows of the folders read, and those hashed
_FOLDERS: set[str] = set()  # the folders whose cache rows are in _MEMO
_CACHE: list[Optional[HashCache]] = [None]


def _cache() -> HashCache:
    c = _CACHE[0]
    if c is None:
        c = _CACHE[0] = HashCache(cache_path())
    return c


def active() -> bool:
    """Whether a run is collecting its inputs (:func:`collecting`)."""
    return bool(_ACTIVE)


def record(path: PathLike, role: str, data=None) -> Optional[str]:
    """Record that the active run(s) read ``path`` as ``role``; its sha256 (None outside
    :func:`collecting`, or for a file that cannot be stat'ed: its reader reports that). ``data``:
    the bytes the reader read (hashed instead of reading the file again)."""
    if not _ACTIVE:
        return None
    t0 = time.perf_counter()
    p = os.path.abspath(os.fspath(path))
    try:
        st = os.stat(p)
    except OSError:
        return None
    key: Key = (p, st.st_size, st.st_mtime_ns, st.st_ino)
    with _LOCK:
        sha = _MEMO.get(key)
        folder = os.path.dirname(p)
        if sha is None and folder not in _FOLDERS:  # one query per folder, not per frame
            _FOLDERS.add(folder)
            _MEMO.update(_cache().folder(folder))
            sha = _MEMO.get(key)
    size, n_hashed = st.st_size, 0
    if sha is None:
        if data is not None:
            size, sha = len(data), sha256_bytes(data)
        else:
            size, sha = sha256_file(p)
        n_hashed = size
    dt = time.perf_counter() - t0
    with _LOCK:
        if n_hashed and size == st.st_size and time.time() - st.st_mtime_ns / 1e9 > RACY_S:
            _MEMO[key] = sha
            _cache().put(key, sha)
        e = Entry(role, p, size, sha)
        for c in _ACTIVE:
            c.add(e)
            c.seconds += dt
            if n_hashed:
                c.hashed += 1
                c.bytes_hashed += n_hashed
            else:
                c.cached += 1
    return sha


def read_bytes(path: PathLike, role: str) -> bytes:
    """The file's bytes, recorded as ``role`` (hashed from these bytes)."""
    data = Path(path).read_bytes()
    record(path, role, data)
    return data


def merge(entries: Iterable[Union[Entry, dict]]) -> None:
    """Add entries recorded elsewhere (a Ray tile's, a scene kept from an earlier job of a sweep)
    to the active collectors."""
    es = [e if isinstance(e, Entry) else Entry(**e) for e in entries]
    with _LOCK:
        for c in _ACTIVE:
            for e in es:
                c.add(e)


@contextlib.contextmanager
def collecting() -> Iterator[Collector]:
    """Record the inputs read inside (nested: each level gets what is read within it; the outer
    ones too). The cache's new entries are written when the outermost one ends."""
    c = Collector()
    with _LOCK:
        if not _ACTIVE and (_CACHE[0] is None or _CACHE[0].path != cache_path()):
            _CACHE[0] = HashCache(cache_path())  # the cache a run's environment names
        _ACTIVE.append(c)
    try:
        yield c
    finally:
        with _LOCK:
            _ACTIVE.remove(c)
            if not _ACTIVE:
                _cache().flush()
                _MEMO.clear()  # a long-lived process (a sweep's, a Ray worker) keeps no run's hashes
                _FOLDERS.clear()


# --------------------------------------------------------------------------- the report

def _role_manifest(es: list[Entry]) -> dict:
    return {"count": len(es), "bytes": sum(e.size for e in es), "sha256": manifest(e.sha256 for e in es)}


def block(entries: Iterable[Entry], collector: Optional[Collector] = None) -> dict:
    """summary.json's ``inputs`` (module doc): ``files`` (the listed roles' files), ``manifests``
    (role -> count, bytes, sha256), ``sha256`` (one hash of all: the roles and their files' or
    manifests' hashes, no paths) and, with the ``collector``, ``hashing`` (files, hashed, cached,
    bytes_hashed, seconds, cache)."""
    by_role: dict[str, list[Entry]] = {}
    for e in sorted(entries, key=lambda e: (e.role, e.path)):
        by_role.setdefault(e.role, []).append(e)
    files, manifests = [], {}
    for role, es in by_role.items():
        if role in MANIFEST_ROLES or len(es) > LISTED_MAX:
            manifests[role] = _role_manifest(es)
        else:
            files += [{"role": e.role, "path": e.path, "size": e.size, "sha256": e.sha256} for e in es]
    parts = sorted([f"{f['role']} {f['sha256']}" for f in files] + [f"{r} {m['sha256']}" for r, m in manifests.items()])
    out = {"files": files, "manifests": manifests, "sha256": sha256_bytes("\n".join(parts).encode())}
    if collector is not None:
        out["hashing"] = {"files": len(collector.entries), "hashed": collector.hashed, "cached": collector.cached,
                          "bytes_hashed": collector.bytes_hashed, "seconds": round(collector.seconds, 4),
                          "cache": _cache().describe()}
    return out


def write_list(path: PathLike, entries: Iterable[Entry]) -> Path:
    """Every input, one tab-separated line each (role, size, sha256, path), sorted by role and path."""
    path = Path(path)
    lines = ["# role\tsize\tsha256\tpath"] + [f"{e.role}\t{e.size}\t{e.sha256}\t{e.path}"
                                              for e in sorted(entries, key=lambda e: (e.role, e.path))]
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, path)
    return path


def read_list(path: PathLike) -> list[Entry]:
    """The entries of a :func:`write_list` file; ValueError naming the line of a malformed one."""
    out = []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):  # one line per input file
        if not line or line.startswith("#"):
            continue
        parts = line.split("\t", 3)
        if len(parts) != 4 or not parts[1].isdigit() or len(parts[2]) != 64:
            raise ValueError(f"{path}:{n}: expected role, size, sha256, path separated by tabs")
        out.append(Entry(parts[0], parts[3], int(parts[1]), parts[2]))
    return out


def compare_lists(old: Iterable[Entry], new: Iterable[Entry]) -> dict[str, list[Entry]]:
    """What changed between two runs' inputs, by (role, path): ``changed`` (the new entry of a file
    whose content differs), ``gone`` (read before, not now), ``added`` (read now only)."""
    a = {(e.role, e.path): e for e in old}
    b = {(e.role, e.path): e for e in new}
    return {"changed": [b[k] for k in sorted(a.keys() & b.keys()) if a[k].sha256 != b[k].sha256],
            "gone": [a[k] for k in sorted(a.keys() - b.keys())],
            "added": [b[k] for k in sorted(b.keys() - a.keys())]}
