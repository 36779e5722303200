"""A write-only file for run.mcap that bypasses the page cache (``O_DIRECT``) where it can.

Why: run.mcap receives ~60 MB per demo run. A buffered write copies every byte into page-cache
pages the kernel must first find; on the VMs we run on, memory not touched for a few seconds is
handed back to the host and costs a fault per page when touched again (writing 64 MB: ~200 ms
of CPU buffered, ~4 ms with ``O_DIRECT``, whose DMA waits on the disk without using the CPU).
The recorder's writer thread then sleeps instead of competing with the diffusion for the cores.

:func:`open_direct` returns a :class:`DirectFile` (the methods mcap's Writer uses: ``write``,
``tell``, ``flush``, ``close``) or, where ``O_DIRECT`` is not available (not Linux, a file
system that refuses it such as older tmpfs), an ordinary buffered file. Each :meth:`flush`
leaves the file exactly as long as the bytes written so far, so a killed run's file ends with
its last complete record, as with a buffered file.
"""
from __future__ import annotations

import errno
import mmap
import os
from pathlib import Path
from typing import BinaryIO, Union

BLOCK = 4096
"""Alignment of O_DIRECT offsets, lengths and buffers (covers 512-byte and 4 KiB sectors)."""


class DirectFile:
    """Appends bytes through a page-aligned staging buffer of ``capacity`` bytes, written out in
    whole blocks with ``pwrite``; the partial last block stays staged (and is rewritten) until
    more bytes complete it."""

    def __init__(self, fd: int, path: Path, capacity: int = 4 << 20):
        self.fd, self.name = fd, str(path)
        self._buf = mmap.mmap(-1, max(BLOCK, capacity - capacity % BLOCK))  # page aligned
        self._mv = memoryview(self._buf)
        self._base = 0  # file offset of the buffer's first byte (a multiple of BLOCK)
        self._fill = 0  # bytes staged
        self.closed = False

    def tell(self) -> int:
        return self._base + self._fill

    def write(self, data) -> int:
        src = memoryview(data).cast("B")
        n, i, cap = len(src), 0, len(self._mv)
        while i < n:
            k = min(n - i, cap - self._fill)
            self._mv[self._fill:self._fill + k] = src[i:i + k]
            self._fill += k
            i += k
            if self._fill == cap:
                self._write_out(pad=False)
        return n

    def flush(self) -> None:
        """Everything written so far goes to the file; its size is then exact."""
        if self.closed:
            return
        self._write_out(pad=True)
        os.ftruncate(self.fd, self.tell())

    def close(self) -> None:
        if self.closed:
            return
        try:
            self.flush()
        finally:
            self.closed = True
            os.close(self.fd)
            try:
                self._mv.release()
                self._buf.close()
            except BufferError:  # a failed write's traceback still holds a slice: the GC frees it,
                pass  # and the write's own error (a full disk) is the one the caller sees

    def __enter__(self) -> "DirectFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _write_out(self, pad: bool) -> None:
        """Write the staged whole blocks (and, with ``pad``, the partial last one, zero-padded);
        keep the partial block staged at the buffer's start."""
        full = self._fill - self._fill % BLOCK
        end = full
        if pad and self._fill > full:
            end = full + BLOCK
            self._mv[self._fill:end] = bytes(end - self._fill)
        if end:
            self._pwrite(self._mv[:end], self._base)
        rest = self._fill - full
        if full:
            self._mv[:rest] = self._mv[full:self._fill]
            self._base += full
            self._fill = rest

    def _pwrite(self, mv: memoryview, offset: int) -> None:
        try:
            done = os.pwrite(self.fd, mv, offset)
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                raise
            import fcntl  # the device wants another alignment: go on without O_DIRECT

            fcntl.fcntl(self.fd, fcntl.F_SETFL, fcntl.fcntl(self.fd, fcntl.F_GETFL) & ~os.O_DIRECT)
            done = os.pwrite(self.fd, mv, offset)
        while done < len(mv):  # a short write (rare): the rest
            done += os.pwrite(self.fd, mv[done:], offset + done)


def open_direct(path: Union[str, Path]) -> Union[DirectFile, BinaryIO]:
    """Create (or truncate) ``path`` for writing: a :class:`DirectFile` where ``O_DIRECT`` works,
    else ``open(path, "wb")``."""
    flag = getattr(os, "O_DIRECT", 0)
    if flag:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | flag, 0o644)
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                raise
        else:
            return DirectFile(fd, Path(path))
    return open(path, "wb")


__all__ = ["DirectFile", "open_direct", "BLOCK"]
