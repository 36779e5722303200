"""The Rerun viewer as a user sees it: the default blueprint's tabs, the errors colour, the log10
series, ``diffuser-lab-inspect --scores`` and ``record.live`` streaming to a running viewer."""
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_DEMO, run_cli

from diffuser_lab.cli.inspect import main as inspect_main
from diffuser_lab.config import ConfigError, default_config
from diffuser_lab.recording.mcap_read import read_run
from diffuser_lab.recording.rerun_log import CONFIDENCE_LUT, UNLABELED_ID, _lab, wrong_color

RERUN = str(Path(sys.executable).with_name("rerun"))
pytestmark = pytest.mark.filterwarnings("ignore:RRD file has no footer")  # what the test server saves


def chunks(path: Path, blueprint: bool = False):
    from rerun.chunk import RrdReader

    r = RrdReader(path)
    if not blueprint:
        return list(r.stream())
    # each send_blueprint is a store of its own, listed in no particular order: the viewer shows the
    # last sent (make_active), the one logged last
    stores = [list(r.stream(store=s)) for s in r.blueprints()]
    def logged(chs) -> int:  # the store's last log_time (ns)
        times = [c.to_record_batch().column("log_time").cast("int64").to_numpy(zero_copy_only=False)
                 for c in chs if "log_time" in c.to_record_batch().schema.names]
        return max((int(t.max()) for t in times if t.size), default=0)

    return max(stores, key=logged) if stores else []


def columns(path: Path) -> dict:
    """{entity path: set of column names} of the recording."""
    out: dict = {}
    for ch in chunks(path):
        out.setdefault(ch.entity_path, set()).update(ch.to_record_batch().schema.names)
    return out


def per_step(path: Path, entity: str, column: str) -> dict:
    """{diffusion_step: value of column} of one entity's temporal rows."""
    out = {}
    for ch in chunks(path):
        if ch.entity_path == entity and not ch.is_static:
            rb = ch.to_record_batch()
            for step, v in zip(rb.column("diffusion_step").to_pylist(), rb.column(column).to_pylist()):
                out[step] = v
    return out


def views(path: Path) -> dict:
    """{view name: {"query": [expressions], "overrides": {entity: {column: value}}}} of the
    default blueprint stored in an .rrd, and "tabs": the tab names in order."""
    by_id: dict = {}
    tabs = []
    for ch in chunks(path, blueprint=True):
        rb = ch.to_record_batch()
        cols = {c: rb.column(c).to_pylist()[-1] for c in rb.schema.names if ":" in c}
        parts = ch.entity_path.strip("/").split("/")
        if parts[0] == "view":
            v = by_id.setdefault(parts[1], {"query": [], "overrides": {}})
            if len(parts) == 2 and "ViewBlueprint:display_name" in cols:
                v["name"] = cols["ViewBlueprint:display_name"][0]
            elif parts[2:] == ["ViewContents"]:
                v["query"] = cols["ViewContents:query"]
            elif "overrides" in parts and cols:
                ent = "/" + "/".join(parts[parts.index("overrides") + 1:parts.index("visualizers")])
                v["overrides"].setdefault(ent, {}).update(cols)
        elif parts[0] == "container" and cols.get("ContainerBlueprint:container_kind") == [1]:  # Tabs
            tabs = [c.split("/")[1] for c in cols["ContainerBlueprint:contents"]]
    out = {v["name"]: v for v in by_id.values() if "name" in v}
    out["tabs"] = [by_id[i]["name"] for i in tabs]
    return out


def shown(query: list, entity: str) -> bool:
    """Rerun's entity filter rules (docs: entity queries): '+'/'-' expressions, a trailing '/**'
    matches the subtree, the most specific matching rule wins, the last among equals."""
    best = None  # (specificity, index, include)
    for i, expr in enumerate(query):
        e = expr.strip()
        include = not e.startswith("-")
        e = e.lstrip("+-").strip()
        if e.endswith("/**"):
            base = e[:-3] or "/"
            hit = entity == base or entity.startswith(base.rstrip("/") + "/")
            spec = (len(base.strip("/").split("/")), 0)
        else:
            hit, spec = entity == e, (len(e.strip("/").split("/")), 1)
        if hit and (best is None or (spec, i) >= best[:2]):
            best = (spec, i, include)
    return bool(best and best[2])


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("viewer") / "run"
    p = run_cli(*SMALL_DEMO, "record=both", "output.quiet=true", f"hydra.run.dir={d}")
    assert p.returncode == 0, p.stderr
    return d


def test_shown_follows_rerun_rules():
    assert shown(["/world/cameras/**"], "/world/cameras/0000/labels")
    assert not shown(["/world/cameras/**", "- /world/cameras/0000/**"], "/world/cameras/0000/labels")
    assert shown(["- /world/**", "/world/a"], "/world/a") and not shown(["/world/a"], "/world/b")


@pytest.mark.slow
def test_cameras_tab_shows_frustums_and_label_images_not_the_depth_clouds(small_run):
    rrd = small_run / "run.rrd"
    cols = columns(rrd)
    depth = {e for e, c in cols.items() if any(n.startswith("DepthImage:") for n in c)}
    labels = {e for e, c in cols.items() if any(n.startswith("SegmentationImage:") for n in c)}
    frustums = {e for e, c in cols.items() if "Pinhole:image_from_camera" in c and e.startswith("/world/cameras/")}
    assert len(depth) == len(labels) == len(frustums) == 10  # SMALL_DEMO: 10 views
    v = views(rrd)
    assert v["tabs"][:7] == ["diffusion: labels", "confidence", "errors", "ground truth", "input + cameras",
                             "depth (back-projected)", "evidence (Bayesian)"]
    for tab in ("input + cameras", "evidence (Bayesian)"):
        q = v[tab]["query"]
        assert all(shown(q, e) for e in labels | frustums), tab
        assert not any(shown(q, e) for e in depth), tab  # the dense clouds hid the points and frustums
    assert shown(v["input + cameras"]["query"], "/world/scene/points")
    assert all(shown(v["depth (back-projected)"]["query"], e) for e in depth)
    # a depth entity back-projects: it carries the camera's pose and pinhole itself
    e = sorted(depth)[0]
    assert {"Pinhole:image_from_camera", "Transform3D:translation", "DepthImage:buffer"} <= cols[e]


@pytest.mark.slow
def test_wrong_points_have_a_colour_no_class_has_and_right_ones_are_grey(small_run):
    from diffuser_lab.data.taxonomy import load_taxonomy, shipped_taxonomies

    log = read_run(small_run / "run.mcap")
    tax = load_taxonomy(log.info.taxonomy)
    rgb, margin = wrong_color(tax.colors)
    d = np.linalg.norm(_lab(np.asarray(rgb)) - _lab(tax.colors), axis=1)
    assert d.min() == pytest.approx(margin) and margin > 40  # CIE76: ~2.3 is a just noticeable difference
    door = _lab(np.array(tax.colors[list(tax.names).index("door")]))
    assert np.linalg.norm(_lab(np.array([230, 30, 30])) - door) < 15  # the old red, for scale: ~ a door
    for name in shipped_taxonomies():  # up to 200 classes: still apart
        t = load_taxonomy(name)
        assert wrong_color(t.colors)[1] > 20, name
    rrd = small_run / "run.rrd"
    packed = per_step(rrd, "/world/diffusion/wrong", "Points3D:colors")
    assert packed and {c for v in packed.values() for c in v} == {(rgb[0] << 24) | (rgb[1] << 16) | (rgb[2] << 8) | 255}
    over = views(rrd)["errors"]["overrides"]["/world/diffusion/labels"]  # one grey for the labels cloud
    (grey,) = over["Points3D:colors"]
    g = np.array([(grey >> 24) & 255, (grey >> 16) & 255, (grey >> 8) & 255])
    assert np.ptp(g) == 0 and np.linalg.norm(_lab(g) - _lab(np.asarray(rgb))) > 40


@pytest.mark.slow
def test_scalars_are_logged_at_every_iteration_and_agree_with_the_recorded_ones(small_run):
    # the plots' scalars at every iteration (the run's side computes them), the Z states on the
    # 1-2-5 schedule; at a recorded iteration the same figures as run.mcap's
    log = read_run(small_run / "run.mcap")
    rrd = small_run / "run.rrd"
    m = {d["iteration"]: d for d in log.metrics}
    last = max(m)
    assert len(m) < last / 4
    got = {k: per_step(rrd, f"/metrics/{k}", "Scalars:scalars")
           for k in ("miou", "accuracy", "confidence", "residual_log10", "changed_per_iter_log10")}
    for k in ("miou", "accuracy", "confidence", "residual_log10"):
        assert sorted(got[k]) == list(range(1, last + 1)), k
    assert sorted(per_step(rrd, "/world/diffusion/labels", "Points3D:class_ids")) == sorted(m)
    for i, d in m.items():
        assert got["miou"][i][0] == pytest.approx(d["miou"], abs=1e-9)
        assert got["accuracy"][i][0] == pytest.approx(d["accuracy"], abs=1e-9)
        assert got["confidence"][i][0] == pytest.approx(d["mean_confidence"], rel=1e-5)
        assert got["residual_log10"][i][0] == pytest.approx(np.log10(d["residual"]), rel=1e-6)
        if d["previous_iteration"] == i - 1 and d["n_changed"]:  # one iteration apart: the same count
            assert got["changed_per_iter_log10"][i][0] == pytest.approx(np.log10(d["n_changed"]))
    ch = got["changed_per_iter_log10"]
    assert ch[1][0] > max(v[0] for i, v in ch.items() if i > last // 2) + 1  # ten times fewer late
    assert got["residual_log10"][1][0] == pytest.approx(0.0)  # relative residual 1 at the first iteration


@pytest.mark.slow
def test_scores_layers_are_the_row_normalised_z(small_run, tmp_path, capsys):
    out = tmp_path / "scores.rrd"
    assert inspect_main([str(small_run), "--to-rrd", str(out), "--scores", "chair,table"]) == 0
    assert "scores of chair, table" in capsys.readouterr().out
    log = read_run(small_run / "run.mcap", z="all")
    names = list(log.info.class_names)
    v = views(out)
    assert v["tabs"][-2:] == ["scores: chair", "scores: table"] and v["scores: chair"]["query"] == ["/world/scores/chair"]
    for cls in ("chair", "table"):
        vals = per_step(out, f"/world/scores/{cls}", "score")
        cols = per_step(out, f"/world/scores/{cls}", "Points3D:colors")
        assert sorted(vals) == log.z_iterations
        for it, Z in log.z.items():
            tot = Z.sum(1)
            want = np.divide(Z[:, names.index(cls)], tot, out=np.zeros(len(Z), np.float32), where=tot > 0)
            got = np.asarray(vals[it], np.float32)
            assert got.min() >= 0.0 and got.max() <= 1.0
            np.testing.assert_allclose(got, want, atol=1e-6)
            lut = CONFIDENCE_LUT[(got * 255).astype(np.uint8)]
            rgb = np.asarray(cols[it], np.uint32)
            np.testing.assert_array_equal(np.stack([rgb >> 24, (rgb >> 16) & 255, (rgb >> 8) & 255], 1), lut)
        assert np.asarray(vals[log.z_iterations[-1]]).max() > 0.5  # the class has points of its own
    # the static positions are the work cloud's
    pos = next(ch for ch in chunks(out) if ch.entity_path == "/world/scores/chair" and ch.is_static)
    assert len(pos.to_record_batch().column("Points3D:positions").to_pylist()[0]) == log.info.n_work_points


@pytest.mark.slow
def test_scores_bad_class_name_is_one_clear_error(small_run, tmp_path, capsys):
    out = tmp_path / "x.rrd"
    assert inspect_main([str(small_run), "--to-rrd", str(out), "--scores", "chair,chiar"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'chiar'" in err[0] and "scannet20" in err[0] and "wall, floor" in err[0]
    assert not out.exists()
    assert inspect_main([str(small_run), "--scores", "chair"]) == 2
    assert "--scores needs --to-rrd" in capsys.readouterr().err


@pytest.mark.parametrize("value,ok", [(None, True), ("off", True), ("spawn", True),
                                      ("rerun+http://127.0.0.1:9876/proxy", True), ("rerun://host:1/proxy", True),
                                      ("http://127.0.0.1:9876", False), ("yes", False), ("rerun+http://", False),
                                      ("rerun+http://127.0.0.1:9876", False),  # Rerun's GrpcSink wants /proxy
                                      ("rerun+http://h:99999/proxy", False)])
def test_record_live_values(value, ok):
    if ok:
        default_config(**{"record.live": value})
    else:
        with pytest.raises(ConfigError, match=r"record\.live=.*expected null, off, spawn or a Rerun gRPC URL"):
            default_config(**{"record.live": value})
    if value is not None and ok and value != "off":
        with pytest.raises(ConfigError, match="record=rerun or record=both"):
            default_config(**{"record.live": value, "record.mode": "mcap"})


@pytest.mark.parametrize("args,expected", [(["record.live=yes"], "expected null, off, spawn or a Rerun gRPC URL"),
                                           (["record=mcap", "record.live=spawn"], "record=rerun or record=both")])
def test_bad_record_live_from_the_command_line_is_one_line(args, expected, tmp_path):
    p = run_cli(*args, cwd=tmp_path)
    assert p.returncode == 2
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("diffuser-lab: error: record.live=") and expected in lines[0]
    assert not (tmp_path / "logs").exists()  # nothing was started


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def rerun_server(tmp_path):
    """A headless Rerun gRPC server that saves what it receives: (url, saved .rrd)."""
    if not Path(RERUN).is_file():
        pytest.skip(f"no Rerun CLI at {RERUN}")
    port, saved, log = _free_port(), tmp_path / "received.rrd", tmp_path / "server.log"
    with open(log, "w") as fh:  # its own process group: the CLI wrapper and the server it starts
        proc = subprocess.Popen([RERUN, "--serve-grpc", "--port", str(port), "--save", str(saved)],
                                stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        t0 = time.monotonic()
        while "Listening for gRPC" not in log.read_text():
            if proc.poll() is not None or time.monotonic() - t0 > 20:
                pytest.skip(f"could not start `rerun --serve-grpc` here: {log.read_text()[-300:]}")
            time.sleep(0.1)
        yield f"rerun+http://127.0.0.1:{port}/proxy", saved, proc
    finally:
        stop(proc, saved)


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
        return True
    except ProcessLookupError:
        return False


def stop(proc: subprocess.Popen, saved: Path) -> None:
    """Let the server write what it has received (the file stops growing), then end its process
    group (the CLI wrapper and the server it runs): SIGINT, then SIGTERM, then SIGKILL, each
    after the group had time to exit (SIGINT is ignored in a shell's background jobs)."""
    last, t0, t_same = -1, time.monotonic(), time.monotonic()
    while time.monotonic() - t0 < 20 and time.monotonic() - t_same < 1.0:
        size = saved.stat().st_size if saved.exists() else 0
        if size != last:
            last, t_same = size, time.monotonic()
        time.sleep(0.1)
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        if not _group_alive(proc.pid):
            break
        os.killpg(proc.pid, sig)
        t = time.monotonic()
        while _group_alive(proc.pid) and time.monotonic() - t < 5:
            proc.poll()  # reaps the wrapper: a zombie leader still counts as the group
            time.sleep(0.05)
    proc.wait(10)


@pytest.mark.slow
def test_live_stream_reaches_a_running_viewer_and_run_rrd_is_still_written(small_demo_scene, tmp_path, rerun_server):
    from diffuser_lab.recording import make_hooks
    from diffuser_lab.runs.pipeline import run

    url, saved, proc = rerun_server
    cfg = default_config(**{"solver.max_iter": 30, "record.interval": 10, "record.mode": "rerun", "record.live": url})
    hooks = make_hooks(cfg, tmp_path / "run")
    try:
        res = run(cfg, scene=small_demo_scene, hooks=hooks)
    finally:
        hooks.close()
    assert hooks.files() == {"rrd": "run.rrd"}
    stop(proc, saved)  # the server writes what it got and exits
    got = per_step(saved, "/world/diffusion/labels", "Points3D:class_ids")
    local = per_step(tmp_path / "run" / "run.rrd", "/world/diffusion/labels", "Points3D:class_ids")
    assert sorted(got) == sorted(local) == [1, 10, 20, 30]
    for it in got:
        np.testing.assert_array_equal(got[it], local[it])
    final = np.where(res.labels < 0, UNLABELED_ID, res.labels.astype(np.int64))  # int16 would wrap 65535
    np.testing.assert_array_equal(got[30], final)
    missing = set(columns(tmp_path / "run" / "run.rrd")) - set(columns(saved))
    assert not missing  # the static part too: cameras, scene, evidence


@pytest.mark.slow
def test_live_to_a_viewer_that_is_not_there_keeps_the_run_and_its_file(small_demo_scene, tmp_path, caplog,
                                                                       monkeypatch):
    from diffuser_lab.recording import make_hooks, rerun_log
    from diffuser_lab.runs.pipeline import run

    # closing waits LIVE_FLUSH_S (60 s) for a viewer that never comes: the same path, waiting 2 s
    monkeypatch.setattr(rerun_log, "LIVE_FLUSH_S", 2.0)
    url = f"rerun+http://127.0.0.1:{_free_port()}/proxy"
    cfg = default_config(**{"solver.max_iter": 10, "record.mode": "rerun", "record.live": url})
    hooks = make_hooks(cfg, tmp_path)
    try:
        run(cfg, scene=small_demo_scene, hooks=hooks)
    finally:
        hooks.close()
    assert hooks.files() == {"rrd": "run.rrd"}
    assert sorted(per_step(tmp_path / "run.rrd", "/world/diffusion/labels", "Points3D:class_ids")) == [1, 2, 5, 10]
    assert any("record.live" in r.getMessage() and url in r.getMessage() for r in caplog.records)


@pytest.mark.slow
def test_live_spawn_starts_a_viewer_and_streams_to_it(tmp_path, rerun_server, monkeypatch):
    """record.live=spawn: rerun's spawn (here replaced: no display to open a window on) starts
    the viewer on LIVE_PORT, without a sink of its own; the recorder streams to it."""
    import rerun.sinks

    from diffuser_lab.recording import rerun_log
    from diffuser_lab.recording.steps import StepTracker

    url, saved, proc = rerun_server
    calls = []
    monkeypatch.setattr(rerun_log, "LIVE_PORT", int(url.rsplit(":", 1)[1].split("/")[0]))
    monkeypatch.setattr(rerun.sinks, "spawn", lambda **kw: calls.append(kw))
    rec = rerun_log.RerunRecorder(tmp_path / "run.rrd", live="spawn")
    assert rec.live == url and calls and calls[0]["connect"] is False and calls[0]["port"] == rerun_log.LIVE_PORT
    pts = np.random.default_rng(0).random((50, 3)).astype(np.float32)
    rec.log_taxonomy(["a", "b"], np.array([[255, 0, 0], [0, 0, 255]], np.uint8))
    rec.log_scene(pts, None, None)
    rec.log_evidence(pts, np.ones(50, bool), np.zeros(50, np.int16))
    Z = np.zeros((50, 2), np.float32)
    Z[:25, 0] = Z[25:, 1] = 1.0
    rec.log_step(StepTracker(50, ["a", "b"]).step(1, Z, 1.0))
    rec.close()
    stop(proc, saved)
    got = per_step(saved, "/world/diffusion/labels", "Points3D:class_ids")
    np.testing.assert_array_equal(got[1], [0] * 25 + [1] * 25)
    assert (tmp_path / "run.rrd").stat().st_size > 0


@pytest.mark.slow
def test_batch_layout_has_its_app_id_a_legend_and_plots_of_every_metric(small_run):
    from rrd_layout import check_layout, static_column

    from diffuser_lab.data.taxonomy import load_taxonomy
    from diffuser_lab.recording.rerun_log import APP_BATCH

    rrd = small_run / "run.rrd"
    gt = np.asarray(static_column(rrd, "/world/scene/ground_truth", "Points3D:class_ids"))
    tax = load_taxonomy(read_run(small_run / "run.mcap").run["taxonomy"])
    v = check_layout(rrd, APP_BATCH, tax, gt[gt != UNLABELED_ID], {
        "mIoU and accuracy so far [%]": ["/metrics/miou", "/metrics/accuracy"],
        "mean confidence": ["/metrics/confidence"],
        "labels changed per iteration, log10": ["/metrics/changed_per_iter_log10"],
        "relative residual |Z_t - Z_t-1|, log10": ["/metrics/residual_log10"]})
    assert "legend" not in v["tabs"] and v["tabs"][0] == "diffusion: labels"


def test_unlabeled_is_a_light_grey_apart_from_every_class_of_every_shipped_taxonomy():
    from diffuser_lab.data.taxonomy import load_taxonomy, shipped_taxonomies
    from diffuser_lab.recording.rerun_log import UNLABELED_RGB, unlabeled_color

    for name in shipped_taxonomies():
        t = load_taxonomy(name)
        rgb = np.asarray(unlabeled_color(t.colors))
        assert np.ptp(rgb) == 0 and _lab(rgb)[0] > 60, name  # a grey, light on the black background
        assert np.linalg.norm(_lab(rgb) - _lab(t.colors), axis=1).min() > 10, name
    assert unlabeled_color(load_taxonomy("scannet20").colors) == UNLABELED_RGB
    assert unlabeled_color(load_taxonomy("ade20k150").colors) != UNLABELED_RGB  # its windowpane is (230, 230, 230)


def test_viewer_screenshots_kinds_compose_and_a_bad_kind_is_one_line(capsys):
    # scripts/viewer_screenshots.py (the documentation's viewer pictures): each kind's overrides
    # make a valid config of the protocol it names; an unknown kind stops before running anything
    import importlib.util

    from conftest import ROOT, compose

    spec = importlib.util.spec_from_file_location("viewer_screenshots", ROOT / "scripts" / "viewer_screenshots.py")
    shots = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(shots)
    assert {k: str(compose(*v).protocol.name) for k, v in shots.KINDS.items()} == {
        "batch": "global_3d", "online": "online", "tiled": "tiled", "tiled-city": "tiled", "single-frame": "single_frame"}
    with pytest.raises(SystemExit) as e:
        shots.main(["/tmp/unused", "--kinds", "batch,nope"])
    assert e.value.code == 2 and "unknown nope" in capsys.readouterr().err


@pytest.mark.slow
def test_scores_run_has_the_confidence_layer_of_its_saved_scores(tmp_path):
    """output.scores=true: run.rrd's ``confidence: scores.npy`` tab shows world/result/confidence, the
    original points with the top score, margin and entropy of the rows scores.npy saved; the rest of
    the batch layout is unchanged."""
    from rrd_layout import check_layout, static_column

    from diffuser_lab.data.taxonomy import load_taxonomy
    from diffuser_lab.method.calibration import confidence
    from diffuser_lab.recording.rerun_log import APP_BATCH, RESULT_CONFIDENCE

    d = tmp_path / "run"
    p = run_cli(*SMALL_DEMO, "scene.voxel_size=0.1", "output.scores=true", "record=rerun", "output.quiet=true",
                f"hydra.run.dir={d}")
    assert p.returncode == 0, p.stderr[-2000:]
    rrd = d / "run.rrd"
    gt = np.asarray(static_column(rrd, "/world/scene/ground_truth", "Points3D:class_ids"))
    v = check_layout(rrd, APP_BATCH, load_taxonomy("scannet20"), gt[gt != UNLABELED_ID],
                     {"confidence: scores.npy": [f"/{RESULT_CONFIDENCE}"],
                      "mean confidence": ["/metrics/confidence"]})
    assert v["tabs"][:3] == ["diffusion: labels", "confidence", "confidence: scores.npy"]
    conf = confidence(np.load(d / "scores.npy"))
    pts = np.asarray(static_column(rrd, f"/{RESULT_CONFIDENCE}", "Points3D:positions"), np.float32)
    assert pts.shape == (len(conf), 3)  # the original points (the diffusion ran on 10 cm voxels)
    for j, name in enumerate(("confidence", "margin", "entropy")):
        np.testing.assert_array_equal(np.asarray(static_column(rrd, f"/{RESULT_CONFIDENCE}", name), np.float32),
                                      conf[:, j])
    colors = np.asarray(static_column(rrd, f"/{RESULT_CONFIDENCE}", "Points3D:colors"), np.uint32)
    lut = CONFIDENCE_LUT[(np.clip(conf[:, 0], 0, 1) * np.float32(255)).astype(np.uint8)].astype(np.uint32)
    np.testing.assert_array_equal(colors >> 8, (lut[:, 0] << 16) | (lut[:, 1] << 8) | lut[:, 2])
