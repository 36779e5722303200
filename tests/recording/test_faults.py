"""A run killed mid-diffusion leaves readable records: summary.json says it did not finish,
run.mcap yields its complete leading iterations."""
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
        [sys.executable, "-m", "diffuser_lab", "n_views=8", "scene.demo.point_spacing=0.08", "solver.max_iter=1000000",
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
