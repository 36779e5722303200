"""The one reader of ``.npy`` files and ``.npz`` members: every array a user hands a run (feature
maps, class probabilities and depth kept as arrays, query sets), a network's cached outputs and the
files a run folder keeps for a later command (``features.npy``, ``features_basis.npz``, ...).

Before anything is allocated, an array's header (shape x dtype) is checked against the bytes the
file holds (a header that lies would ask for terabytes), a compressed ``.npz`` member may not claim
more than deflate expands to (1,032 : 1), and arrays of Python objects are refused (nothing is
unpickled). Then what the caller expects: the number of dimensions, the dtype's kinds (``"f"``,
``"iu"``, ``"US"``) and the sizes (``None``: any). Anything else is one ValueError naming the file
(and the member: ``path [key]``) and what was expected; a missing file is a FileNotFoundError.

A file read is recorded as the run's input of ``role`` (:func:`diffuser_lab.data.inputs.record`;
``None``: not an input, e.g. a cache or a run's own output read back). Arrays come back writable
(a ``.npy`` may be memory-mapped read-only instead: ``mmap=True``).
"""
from __future__ import annotations

import contextlib
import struct
import threading
import zipfile
import zlib
from pathlib import Path
from typing import Iterator, Optional, Sequence, Union

import numpy as np

from . import inputs

__all__ = ["read_array", "open_npz", "Npz", "check_array"]

Shape = Sequence[Optional[int]]
_ZIP_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, NotImplementedError, RuntimeError,
               KeyError, IndexError, struct.error, zlib.error, UnicodeDecodeError)
"""What zipfile raises on a damaged archive (a version it does not know, a truncated directory, ...)."""
_KINDS = {"f": "floats", "iu": "integers", "SU": "strings", "fiu": "numbers", "b": "booleans"}
DEFLATE_MAX = 1100
"""The most bytes a compressed member may claim per stored byte (deflate: 1,032 at most), past a 4 KiB allowance."""
_HEADER_LOCK = threading.Lock()
"""One header parsed at a time: numpy parses it with ``ast.literal_eval``, whose AST constructor in
CPython 3.11 keeps its recursion depth in state shared by the threads, so two frames read ahead at
once could fail with "SystemError: AST constructor recursion depth mismatch" (python/cpython#106905)."""


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else ""


def check_array(arr: np.ndarray, where: str, what: str, *, ndim: Union[int, Sequence[int], None] = None,
                kinds: Optional[str] = None, dtypes: Optional[Sequence] = None, shape: Optional[Shape] = None,
                expected: Optional[str] = None) -> np.ndarray:
    """``arr`` itself when it has ``ndim`` dimensions (an int or the allowed ints), a dtype of one of
    ``kinds`` (and one of ``dtypes`` when given) and the ``shape`` (``None`` entries: any size); else
    one ValueError ``"<where>: <what> of shape S dtype D, expected <expected>"`` (``expected``: the
    caller's words, else made from the checks)."""
    dims = (ndim,) if isinstance(ndim, int) else tuple(ndim) if ndim is not None else None
    if shape is not None:
        dims = (len(shape),)
    ok = ((dims is None or arr.ndim in dims) and (kinds is None or arr.dtype.kind in kinds)
          and (dtypes is None or any(arr.dtype == np.dtype(t) for t in dtypes))
          and (shape is None or all(s is None or s == n for s, n in zip(shape, arr.shape))))
    if not ok:
        if expected is None:
            size = ("(" + ", ".join("*" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
                    if shape is not None else " or ".join(f"{d}-d" for d in dims) if dims else "an array")
            expected = size + (f" {_KINDS.get(''.join(sorted(kinds)), f'of dtype kind {kinds}')}" if kinds else "") + (
                f" ({' or '.join(np.dtype(t).name for t in dtypes)})" if dtypes else "")
        raise ValueError(f"{where}: {what} of shape {arr.shape} dtype {arr.dtype}, expected {expected}")
    return arr


def _npy(fh, size: int, where: str, mmap_path: Optional[Path] = None) -> np.ndarray:
    """The array of an open ``.npy`` stream of ``size`` bytes, its header's shape x dtype checked
    against the bytes there before anything is allocated; ``mmap_path``: the file itself, mapped
    read-only instead of read."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        if version not in ((1, 0), (2, 0), (3, 0)):
            raise ValueError(f"format version {version}, expected 1.0, 2.0 or 3.0")
        start, width = fh.tell(), 2 if version == (1, 0) else 4
        hlen = int.from_bytes(fh.read(width), "little")
        if hlen > size - start - width:  # read before it is checked, a lying length allocates gigabytes
            raise ValueError(f"header length {hlen:,} beyond the file's {size:,} bytes")
        fh.seek(start)
        with _HEADER_LOCK:
            shape, fortran, dtype = (fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0)(fh)
    except Exception as e:  # noqa: BLE001 - numpy's header parser raises what its tokenizer or literal_eval does
        raise ValueError(f"{where}: not a .npy file ({type(e).__name__}: {_first_line(e)})") from None
    if dtype.hasobject:
        raise ValueError(f"{where}: array of Python objects ({dtype}), expected numbers or strings")
    need = int(np.prod(shape, dtype=object)) * dtype.itemsize
    offset = fh.tell()
    have = size - offset
    if need != have:
        raise ValueError(f"{where}: header says shape {shape} of {dtype} = {need:,} bytes, the file holds {have:,}")
    order = "F" if fortran else "C"
    if mmap_path is not None and need:
        return np.memmap(mmap_path, dtype, "r", offset, shape, order)
    buf = bytearray(need)
    got = fh.readinto(buf)
    if got != need:
        raise ValueError(f"{where}: header says {need:,} bytes of {dtype}, the file ends after {got:,}")
    return np.frombuffer(buf, dtype).reshape(shape, order=order)


def _exists(path: Path, what: str) -> None:
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} does not exist")


class Npz:
    """An open ``.npz`` (:func:`open_npz`): ``files`` its member names (without ``.npy``), ``name in
    npz``, :meth:`read` a member checked (shape x dtype against its bytes, then the caller's
    expectations), ``npz[name]`` one without expectations."""

    def __init__(self, zf: zipfile.ZipFile, path: Path, what: str):
        self._z, self.path, self.what = zf, path, what
        self.files = [n[:-4] for n in zf.namelist() if n.endswith(".npy")]

    def __contains__(self, name: str) -> bool:
        return name in self.files

    def __getitem__(self, name: str) -> np.ndarray:
        return self.read(name)

    def read(self, name: str, **expect) -> np.ndarray:
        """Member ``name`` (ValueError naming the file when absent); ``expect``: :func:`check_array`'s
        ``ndim``, ``kinds``, ``shape``, ``expected``."""
        where = f"{self.path} [{name}]"
        if name not in self.files:
            raise ValueError(f"{self.path}: no {name!r} array (has: {', '.join(self.files) or 'nothing'}), "
                             f"expected {self.what}")
        try:
            info = self._z.getinfo(f"{name}.npy")
            if info.file_size > DEFLATE_MAX * info.compress_size + 4096:
                raise ValueError(f"{where}: says {info.file_size:,} bytes from {info.compress_size:,} compressed, "
                                 f"more than deflate can expand to")
            with self._z.open(info) as fh:
                arr = _npy(fh, info.file_size, where)
        except _ZIP_ERRORS as e:
            raise ValueError(f"{where}: unreadable ({type(e).__name__}: {_first_line(e)}), expected {self.what}") from None
        return check_array(arr, where, name, **expect) if expect else arr


@contextlib.contextmanager
def open_npz(path: Union[str, Path], what: str, role: Optional[str] = "frames") -> Iterator[Npz]:
    """The ``.npz`` at ``path`` (:class:`Npz`), recorded as the run's input of ``role`` (None: not an
    input); ``what`` names what it should hold in the errors (``"a .npz query file"``). Not a zip
    file, or a damaged one: one ValueError naming it."""
    path = Path(path)
    _exists(path, what)
    if role is not None:
        inputs.record(path, role)
    try:
        zf = zipfile.ZipFile(path)
    except (*_ZIP_ERRORS, ValueError) as e:
        with open(path, "rb") as fh:
            if fh.read(6) == b"\x93NUMPY":
                raise ValueError(f"{path}: a single array, expected {what}") from None
        raise ValueError(f"{path}: unreadable .npz ({type(e).__name__}: {_first_line(e)}), expected {what}") from None
    with zf:
        yield Npz(zf, path, what)


def read_array(path: Union[str, Path], what: str, key: Optional[str] = None, role: Optional[str] = "frames", *,
               mmap: bool = False, **expect) -> np.ndarray:
    """A ``.npy`` file, or a ``.npz``'s array ``key`` (absent: its first), checked (module doc).

    Args:
        what: what the file holds, for the errors ("depth image", "feature map").
        key: the ``.npz`` member to read (absent or None: the first).
        role: the run's input role (None: not an input).
        mmap: a ``.npy`` mapped read-only, not read (a run folder's large arrays).
        expect: :func:`check_array`'s ``ndim``, ``kinds``, ``shape``, ``expected``.
    """
    path = Path(path)
    if path.suffix.lower() == ".npz":
        with open_npz(path, f"a {what}", role) as z:
            if not z.files:
                raise ValueError(f"{path}: empty .npz, expected a {what}")
            name = key if key is not None and key in z else z.files[0]
            return check_array(z.read(name), f"{path} [{name}]", what, **expect) if expect else z.read(name)
    _exists(path, what)
    if role is not None:
        inputs.record(path, role)
    try:
        with open(path, "rb") as fh:
            arr = _npy(fh, path.stat().st_size, str(path), path if mmap else None)
    except OSError as e:
        raise ValueError(f"{path}: unreadable ({type(e).__name__}: {_first_line(e)}), expected a {what}") from None
    return check_array(arr, str(path), what, **expect) if expect else arr
