"""How run.mcap reaches the disk (issue 4): the O_DIRECT file and the glibc heap setting."""
import errno
import os
import platform
import subprocess
import sys

import numpy as np
import pytest

from diffuser_lab.recording import direct_file
from diffuser_lab.recording.direct_file import BLOCK, DirectFile, open_direct


def _writes(rng, n=60):
    """Byte strings of awkward sizes: empty, 1 byte, around a block, around the buffer, larger."""
    sizes = [0, 1, BLOCK - 1, BLOCK, BLOCK + 1, 3 * BLOCK, 65536 - 3, 65536, 65536 + 7, 200_000]
    for i in range(n):
        yield rng.integers(0, 256, sizes[i % len(sizes)] if i < 20 else int(rng.integers(0, 150_000)),
                           dtype=np.uint8).tobytes()


@pytest.mark.parametrize("capacity", [BLOCK, 65536, 1 << 20])
def test_direct_file_holds_exactly_the_bytes_written_at_every_flush(tmp_path, capacity):
    path = tmp_path / "x.bin"
    f = open_direct(path)
    if isinstance(f, DirectFile):  # the staging buffer's size is the interesting variable
        f.close()
        f = DirectFile(os.open(path, os.O_WRONLY | os.O_TRUNC | os.O_DIRECT), path, capacity)
    rng = np.random.default_rng(capacity)
    expect = bytearray()
    for i, data in enumerate(_writes(rng)):
        assert f.write(memoryview(data) if i % 2 else data) == len(data)
        expect += data
        assert f.tell() == len(expect)
        if i % 3 == 0:
            f.flush()
            assert path.read_bytes() == bytes(expect)  # a killed run leaves exactly this
    f.close()
    assert path.read_bytes() == bytes(expect)
    f.close()  # twice is harmless


def test_open_direct_falls_back_to_a_buffered_file(tmp_path, monkeypatch):
    real_open = os.open

    def refuse(path, flags, *args):
        if flags & getattr(os, "O_DIRECT", 0):
            raise OSError(errno.EINVAL, "Invalid argument")  # what tmpfs says
        return real_open(path, flags, *args)

    monkeypatch.setattr(direct_file.os, "open", refuse)
    with open_direct(tmp_path / "y.bin") as f:
        assert not isinstance(f, DirectFile)
        f.write(b"abc")
    assert (tmp_path / "y.bin").read_bytes() == b"abc"


@pytest.mark.skipif(not hasattr(os, "O_DIRECT"), reason="no O_DIRECT on this platform")
def test_direct_file_goes_on_without_o_direct_when_the_device_refuses_the_alignment(tmp_path, monkeypatch):
    f = open_direct(tmp_path / "z.bin")
    if not isinstance(f, DirectFile):
        f.close()
        pytest.skip(f"{tmp_path} does not take O_DIRECT")
    real_pwrite, calls = os.pwrite, []

    def pwrite(fd, data, offset):
        calls.append(offset)
        if len(calls) == 1:
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_pwrite(fd, data, offset)

    monkeypatch.setattr(direct_file.os, "pwrite", pwrite)
    payload = np.arange(300_000, dtype=np.uint32).tobytes()
    f.write(payload)
    f.close()
    assert (tmp_path / "z.bin").read_bytes() == payload and len(calls) >= 2


def test_write_errors_reach_the_caller(tmp_path, monkeypatch):
    f = open_direct(tmp_path / "e.bin")
    if not isinstance(f, DirectFile):
        f.close()
        pytest.skip(f"{tmp_path} does not take O_DIRECT")

    def full(fd, data, offset):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(direct_file.os, "pwrite", full)
    f.write(b"x" * 10)
    with pytest.raises(OSError, match="No space"):
        f.flush()
    g = open_direct(tmp_path / "c.bin")  # at close, the write's error is the one raised (the failed
    g.write(b"x" * 5000)  # write's traceback holds a slice of the buffer, which cannot then be unmapped)
    with pytest.raises(OSError, match="No space"):
        g.close()
    assert g.closed


_FAULTS = """
import resource, sys
import numpy as np
from diffuser_lab.recording.heap import retain_freed_memory
print(retain_freed_memory(int(sys.argv[1])))
def churn():  # what a recorded iteration does: a few MB-sized buffers alive together, then freed
    bufs = [np.ones(3_500_000 // 8) for _ in range(4)]
    del bufs
churn()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    churn()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_retained_heap_stops_the_page_faults_of_buffer_churn():
    def faults(mb):
        p = subprocess.run([sys.executable, "-c", _FAULTS, str(mb)], capture_output=True, text=True, check=True)
        applied, n = p.stdout.split()
        return applied, int(n)

    off, on = faults(0), faults(64)
    assert off[0] == "False" and on[0] == "True"
    # 10 x 14 MB: ~35,000 faults when the heap gives the pages back each time, ~0 when it keeps them
    assert off[1] > 10_000, off
    assert on[1] < off[1] / 10, (on, off)


@pytest.mark.parametrize("compiled", [True, False])
def test_float16_conversion_is_numpys_bit_for_bit(compiled, monkeypatch):
    """Z states in float16 are converted without numpy's slow subnormal path, to the same bits:
    normals, subnormals, ties (to even) at every float16 subnormal step, the largest values,
    zero (and, compiled, signs and overflow)."""
    from diffuser_lab.backends import numba as nb
    from diffuser_lab.backends.records import to_float16

    rng = np.random.default_rng(0)
    a = np.concatenate([rng.random(20000), 10 ** rng.uniform(-12, 0, 80000), np.arange(2049) * 2.0**-25,
                        [2.0**-14 * (1 - 2**-12), 2.0**-14, 65504, 1.0, 0.0, 1e-45]]).astype(np.float32)
    if compiled:
        if not nb.available():
            pytest.skip("numba not importable or DIFFUSER_LAB_NUMBA=0")
        a = np.concatenate([a, -a[:1000], np.float32([65519, 65520, 1e6, np.inf, -np.inf, -0.0])])
    else:
        monkeypatch.setattr(nb, "available", lambda: False)
    with np.errstate(over="ignore"):
        want = a.astype("<f2")
    got = to_float16(a)
    assert got.dtype == np.dtype("<f2")
    np.testing.assert_array_equal(got.view(np.uint16), want.view(np.uint16))
