"""The inputs recorder (diffuser_lab/data/inputs.py): what the readers record, hashed once, the
cache by (path, size, mtime_ns, inode) shared by processes, the manifests and summary.json's block."""
import hashlib
import multiprocessing
import os
import threading
import time

import numpy as np
import pytest
from PIL import Image

from diffuser_lab.data import inputs
from diffuser_lab.data.images import read_depth_png
from diffuser_lab.data.poses import read_pose_c2w


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A cache file of this test's own (the recorder reopens it when a run starts)."""
    path = tmp_path / "hashes.sqlite"
    monkeypatch.setenv("DIFFUSER_LAB_HASH_CACHE", str(path))
    return path


def _old(path, age_s=60.0):
    """Back-date a file: written more than inputs.RACY_S ago, its hash may be cached."""
    t = time.time() - age_s
    os.utime(path, (t, t))
    return path


def _depth(path, value=1000):
    Image.fromarray(np.full((6, 8), value, np.uint16)).save(path)
    return _old(path)


def test_nothing_is_recorded_outside_a_run(tmp_path, cache):
    p = _depth(tmp_path / "d.png")
    assert inputs.record(p, "frames") is None and not inputs.active()
    read_depth_png(p, 1000.0)  # a library call: no hashing, no cache
    assert not cache.exists()


def test_readers_record_their_files_with_the_bytes_they_read(tmp_path, cache):
    d = _depth(tmp_path / "d.png")
    pose = tmp_path / "p.txt"
    np.savetxt(pose, np.eye(4))
    with inputs.collecting() as got:
        depth = read_depth_png(d, 1000.0)
        read_pose_c2w(pose)
        read_depth_png(d, 1000.0)  # read twice: one entry
    assert depth.shape == (6, 8) and float(depth[0, 0]) == 1.0
    rows = got.rows()
    assert [(e.role, os.path.basename(e.path)) for e in rows] == [("frames", "d.png"), ("frames", "p.txt")]
    assert rows[0].sha256 == hashlib.sha256(d.read_bytes()).hexdigest() and rows[0].size == d.stat().st_size
    assert got.hashed == 2 and got.cached == 1  # the second read: this process's memo


def test_the_cache_answers_a_second_run_and_not_an_edited_file(tmp_path, cache):
    d = _depth(tmp_path / "d.png")
    with inputs.collecting() as first:
        inputs.record(d, "frames")
    assert first.hashed == 1 and cache.is_file()
    with inputs.collecting() as second:  # a later run: from the file's cache
        inputs.record(d, "frames")
    assert second.hashed == 0 and second.cached == 1
    assert second.rows()[0].sha256 == first.rows()[0].sha256
    _depth(d, value=1001)  # edited in place: another mtime
    with inputs.collecting() as third:
        sha = inputs.record(d, "frames")
    assert third.hashed == 1 and sha != first.rows()[0].sha256
    assert sha == hashlib.sha256(d.read_bytes()).hexdigest()


def test_a_file_written_just_now_is_not_cached(tmp_path, cache):
    p = tmp_path / "new.txt"
    p.write_text("1 0 0\n0 1 0\n0 0 1\n")  # mtime: now (an edit within its clock tick would keep it)
    for _ in range(2):
        with inputs.collecting() as got:
            inputs.record(p, "intrinsics")
        assert got.hashed == 1


def test_threads_record_side_by_side(tmp_path, cache):
    files = [_depth(tmp_path / f"{i}.png", 1000 + i) for i in range(40)]
    with inputs.collecting() as got:
        ts = [threading.Thread(target=lambda fs=files[k::4]: [read_depth_png(f, 1000.0) for f in fs]) for k in range(4)]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
    assert len(got.rows()) == 40 and got.hashed == 40
    assert {e.sha256 for e in got.rows()} == {hashlib.sha256(f.read_bytes()).hexdigest() for f in files}


def _hash_in_child(paths, cache_path, q):
    os.environ["DIFFUSER_LAB_HASH_CACHE"] = cache_path
    with inputs.collecting() as got:
        for p in paths:
            inputs.record(p, "frames")
    q.put((got.hashed, got.cached))


def test_processes_share_the_cache(tmp_path, cache):
    """A sweep's jobs side by side (the joblib or Ray launcher): each process adds and reads."""
    files = [str(_depth(tmp_path / f"{i}.png", 2000 + i)) for i in range(30)]
    ctx = multiprocessing.get_context("spawn")
    q = ctx.Queue()
    procs = [ctx.Process(target=_hash_in_child, args=(files, str(cache), q)) for _ in range(3)]
    for p in procs:
        p.start()
    got = [q.get(timeout=60) for _ in procs]
    for p in procs:
        p.join(60)
    assert all(p.exitcode == 0 for p in procs) and all(h + c == 30 for h, c in got)
    with inputs.collecting() as later:  # every file is in the cache now, whoever hashed it
        for f in files:
            inputs.record(f, "frames")
    assert later.hashed == 0 and later.cached == 30


def test_a_cache_that_cannot_be_opened_is_switched_off(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("x")
    monkeypatch.setenv("DIFFUSER_LAB_HASH_CACHE", str(tmp_path / "file" / "hashes.sqlite"))  # under a file
    d = _depth(tmp_path / "d.png")
    with inputs.collecting() as got:
        sha = inputs.record(d, "frames")
        block = inputs.block(got.rows(), got)
    assert sha == hashlib.sha256(d.read_bytes()).hexdigest()
    assert block["hashing"]["cache"].startswith("off (")


def test_manifest_is_the_sorted_hashes_and_their_count():
    hs = [hashlib.sha256(bytes([i])).hexdigest() for i in range(3)]
    want = hashlib.sha256((f"3\n" + "".join(h + "\n" for h in sorted(hs))).encode()).hexdigest()
    assert inputs.manifest(hs) == want == inputs.manifest(hs[::-1])
    assert inputs.manifest(hs[:2]) != want


def test_block_lists_few_files_and_makes_manifests_of_many(tmp_path):
    def e(role, name, sha):
        return inputs.Entry(role, str(tmp_path / name), 10, sha * 64)

    es = [e("frames", f"{i}.png", "a") for i in range(3)] + [e("mesh", "m.ply", "b")] + \
         [e("intrinsics", f"{i}.txt", "c") for i in range(inputs.LISTED_MAX + 1)]
    block = inputs.block(es)
    assert [f["role"] for f in block["files"]] == ["mesh"]
    assert block["manifests"]["frames"] == {"count": 3, "bytes": 30, "sha256": inputs.manifest(["a" * 64] * 3)}
    assert block["manifests"]["intrinsics"]["count"] == inputs.LISTED_MAX + 1
    moved = [inputs.Entry(x.role, x.path.replace(str(tmp_path), "/elsewhere"), x.size, x.sha256) for x in es]
    assert inputs.block(moved)["sha256"] == block["sha256"]  # paths are not part of it
    assert inputs.block(es[:-1])["sha256"] != block["sha256"]


def test_the_list_file_reads_back_and_compares(tmp_path):
    a = [inputs.Entry("frames", "/d/0.png", 5, "a" * 64), inputs.Entry("frames", "/d/1.png", 5, "b" * 64)]
    b = [inputs.Entry("frames", "/d/0.png", 5, "c" * 64), inputs.Entry("mesh", "/d/m.ply", 9, "d" * 64)]
    path = inputs.write_list(tmp_path / inputs.LIST_NAME, a)
    assert inputs.read_list(path) == a
    diff = inputs.compare_lists(a, b)
    assert [x.path for x in diff["changed"]] == ["/d/0.png"] and [x.path for x in diff["gone"]] == ["/d/1.png"]
    assert [x.path for x in diff["added"]] == ["/d/m.ply"]
    path.write_text("frames\tx\tnot-a-hash\t/d/0.png\n")
    with pytest.raises(ValueError, match=r"inputs.tsv:1: expected role, size, sha256, path"):
        inputs.read_list(path)
