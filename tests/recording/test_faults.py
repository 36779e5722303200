"""Long runs survive faults (issue 39, item 5): a run killed mid-diffusion leaves readable records
(summary.json says it did not finish, run.mcap yields its complete leading iterations); a tiled
driver killed mid-run resumes to equal labels; a record that cannot be written ends in one error
line after the labels; two runs started at the same instant never share a folder."""
import json
import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import ROOT


@pytest.mark.slow
def test_killed_run_leaves_running_summary_and_readable_mcap(tmp_path):
    run_dir = tmp_path / "run"
    env = dict(os.environ)
    env.pop("HYDRA_FULL_ERROR", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "diffuser_lab", "n_views=8", "scene.options.point_spacing=0.08", "solver.max_iter=1000000",
         "solver.tol=0", "record=mcap", "record.interval=5", f"hydra.run.dir={run_dir}"],
        cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        mcap = run_dir / "run.mcap"
        deadline = time.time() + 120
        while time.time() < deadline and not (mcap.is_file() and mcap.stat().st_size > 2_000_000):
            time.sleep(0.2)
        assert mcap.is_file() and mcap.stat().st_size > 2_000_000, "the run did not start recording"
        assert proc.poll() is None, "the run ended before it could be killed"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    s = json.loads((run_dir / "summary.json").read_text())  # atomically replaced: always whole
    assert s["status"] == "running"
    # the recording process (diffuser_lab.recording.process) outlives the run: it finishes the
    # file with the iterations it received; wait until it is done writing
    size, still = -1, 0
    while still < 5 and time.time() < deadline + 60:
        now = mcap.stat().st_size
        still, size = (still + 1 if now == size else 0), now
        time.sleep(0.2)
    p = subprocess.run([sys.executable, "-m", "diffuser_lab.cli.inspect", str(run_dir)], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "did not finish" in p.stdout and "Traceback" not in p.stderr

    from diffuser_lab.recording.mcap_read import read_run

    log = read_run(mcap, z="all")
    assert log.summary is None and len(log.z_iterations) >= 2
    assert log.z_iterations[:2] == [1, 5]
    last = log.z_iterations[-1]
    assert log.z[last].shape[0] > 1000


def test_two_runs_started_in_the_same_microsecond_get_their_own_folders(tmp_path):
    """hydra.run.dir's resolver makes the folder as it names it (os.mkdir): the second run started at
    the same instant finds it made and takes the next stamp."""
    import datetime

    from diffuser_lab.config import claim_run_dir

    t = datetime.datetime(2026, 12, 4, 9, 9, 1, 969155)
    a, b = (claim_run_dir(str(tmp_path), "diffuser_demo", now=t) for _ in range(2))
    assert a != b and os.path.isdir(a) and os.path.isdir(b)
    assert os.path.basename(a) == "09-09-01-969155_diffuser_demo" and os.path.basename(b) > os.path.basename(a)
    assert "diffuser_lab.run_dir:" in (ROOT / "conf" / "config.yaml").read_text()  # the CLI's run folders


@pytest.mark.slow
def test_a_record_that_cannot_be_written_ends_in_one_error_line_after_the_labels(tmp_path):
    """A full disk (RLIMIT_FSIZE under run.mcap's and run.rrd's size, as a full folder answers:
    EFBIG/ENOSPC): labels.npy and summary.json are written and equal a run without records, then one
    ``diffuser-lab: error:`` line names the run folder and the records; exit 1."""
    import resource

    import numpy as np

    def full_disk():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG), as on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))

    args = [sys.executable, "-m", "diffuser_lab", "scene.options.n_views=10", "scene.options.point_spacing=0.08",
            "solver.max_iter=60", "output.labels_ply=false"]
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "RUST_LOG")}
    p = subprocess.run([*args, f"hydra.run.dir={tmp_path / 'full'}"], cwd=ROOT, env=env, preexec_fn=full_disk,
                       capture_output=True, text=True, timeout=300)
    ref = subprocess.run([*args, "record=off", f"hydra.run.dir={tmp_path / 'ref'}"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=300)
    assert ref.returncode == 0, ref.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 1 and len(lines) == 1, p.stderr
    assert lines[0].startswith("diffuser-lab: error: ") and str(tmp_path / "full") in lines[0]
    assert "run.mcap" in lines[0] and "File too large" in lines[0]
    np.testing.assert_array_equal(np.load(tmp_path / "full" / "labels.npy"), np.load(tmp_path / "ref" / "labels.npy"))
    s = json.loads((tmp_path / "full" / "summary.json").read_text())
    assert s["status"] == "ok" and s["records"]["errors"]  # the run itself finished


@pytest.mark.slow
def test_a_tiled_driver_killed_mid_run_resumes_to_equal_labels(tmp_path):
    """SIGKILL to a tiled run once its first tiles are written; tiling.resume finishes it in a new
    folder: the labels equal an undisturbed run's, the finished tiles kept."""
    import numpy as np

    args = [sys.executable, "-m", "diffuser_lab", "scene.options.n_views=10", "scene.options.point_spacing=0.08",
            "solver.max_iter=60", "protocol=tiled", "tiling.size=1.5", "record=off", "output.labels_ply=false"]
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    killed = tmp_path / "killed"
    proc = subprocess.Popen([*args, f"hydra.run.dir={killed}"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and len(list((killed / "tiles").glob("*_*.npz"))) < 2 and proc.poll() is None:
            time.sleep(0.05)
        assert proc.poll() is None, "the run ended before it could be killed"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    done = {f.name: f.stat().st_mtime_ns for f in (killed / "tiles").glob("*_*.npz")}
    assert not (killed / "labels.npy").exists() and done
    r = subprocess.run([*args, f"tiling.resume={killed}", f"hydra.run.dir={tmp_path / 'resumed'}"], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=300)
    ref = subprocess.run([*args, f"hydra.run.dir={tmp_path / 'ref'}"], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=300)
    assert r.returncode == 0 and ref.returncode == 0, r.stderr + ref.stderr
    np.testing.assert_array_equal(np.load(tmp_path / "resumed" / "labels.npy"), np.load(tmp_path / "ref" / "labels.npy"))
    status = {t["id"]: t["status"] for t in json.loads((tmp_path / "resumed" / "summary.json").read_text())["tiling"]["tiles"]}
    assert all(status[n[:-4]] == "resumed" for n in done) and "done" in status.values()
    assert all((killed / "tiles" / n).stat().st_mtime_ns == m for n, m in done.items())


def test_a_file_writer_that_stops_answering_ends_the_flush_with_an_error(tmp_path, monkeypatch):
    """Rerun's flush on a dead file writer can wait for ever (a full disk, 1 run in 3): closing run.rrd
    flushes FILE_FLUSH_STALL_S at a time while the file grows, then gives up with an error, and keeps
    the stream (dropping it would disconnect it, which waits on the same writer)."""
    from diffuser_lab.recording import rerun_log

    class Stream:
        calls = 0

        def flush(self, timeout_sec):
            self.calls += 1
            if self.calls <= 2:  # the file grows during the first two waits, then stops
                with open(path, "ab") as f:
                    f.write(b"x" * 10)
            raise RuntimeError("Flush timed out - not all log messages were sent")

    path = tmp_path / "run.rrd"
    path.write_bytes(b"")
    rec = object.__new__(rerun_log.RerunRecorder)
    rec.path, rec.rec = path, Stream()
    monkeypatch.setattr(rerun_log, "_ABANDONED", [])
    with pytest.raises(RuntimeError, match="file writer stopped .*20 bytes"):
        rec._flush_file()
    assert rec.rec.calls == 3 and rerun_log._ABANDONED == [rec.rec]
