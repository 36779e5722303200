"""Taxonomies (shipped, from a file, from the data's ids) and the mappings between them."""
import csv
import json
import warnings

import numpy as np
import pytest
from conftest import SMALL_DEMO, run_cli
from datasets import make_world, write_scannet
from PIL import Image

from diffuser_lab.config import ConfigError
from diffuser_lab.data.mapping import (
    load_mapping,
    mapping_header,
    native_mapping,
    relabel_scene,
    shipped_mappings,
)
from diffuser_lab.data.scene import IGNORE, SCANNET20
from diffuser_lab.data.taxonomy import (
    generated_colors,
    load_taxonomy,
    resolve_taxonomy,
    shipped_taxonomies,
)
from diffuser_lab.runs.resolve import default_config

COUNTS = {"scannet20": 20, "nyu40": 40, "scannet200": 200, "cityscapes19": 19, "ade20k150": 150, "mseg194": 194}


@pytest.mark.parametrize("name", sorted(COUNTS))
def test_shipped_taxonomy_loads_with_unique_names_and_colours(name):
    tax = load_taxonomy(name)
    assert name in shipped_taxonomies() and tax.name == name
    assert tax.num_classes == COUNTS[name] == len(tax.colors)
    assert len({n.lower() for n in tax.names}) == tax.num_classes
    assert len({tuple(c) for c in tax.colors.tolist()}) == tax.num_classes
    assert tax.colors.dtype == np.uint8 and tax.colors.shape == (tax.num_classes, 3)


def test_shipped_taxonomies_match_their_sources():
    s20 = load_taxonomy("scannet20")
    assert s20.names == SCANNET20.names and (s20.colors == SCANNET20.colors).all() and s20.ids is None
    nyu = load_taxonomy("nyu40")
    assert nyu.ids == tuple(range(1, 41)) and nyu.ignore_ids == (0,) and nyu.names[23] == "refridgerator"
    s200 = load_taxonomy("scannet200")
    assert s200.ids[:3] == (1, 2, 3) and s200.ids[-1] == 1191 and s200.names[:3] == ("wall", "chair", "floor")
    cs = load_taxonomy("cityscapes19")
    assert cs.names[0] == "road" and tuple(cs.colors[0]) == (128, 64, 128) and cs.ignore_ids == (255,)
    ade = load_taxonomy("ade20k150")
    assert ade.names[:4] == ("wall", "building", "sky", "floor") and ade.names[-1] == "flag"
    mseg = load_taxonomy("mseg194")
    assert mseg.names[0] == "backpack" and mseg.names[-1] == "window_blind" and "chair_other" in mseg.names


def _raw_rows(path):
    with open(path, newline="", encoding="utf-8") as f:
        lines = [ln for ln in f.read().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    return list(csv.DictReader(lines))


@pytest.mark.parametrize("name", shipped_mappings())
def test_shipped_mapping_checked_against_its_taxonomies(name):
    keys = mapping_header(name)
    src, dst = load_taxonomy(keys["source"]), load_taxonomy(keys["target"])
    m = load_mapping(name, dst)  # every target a class of dst or ignore (else ValueError)
    assert m.target is dst and m.source_taxonomy == src.name
    ids = [int(r["source_id"]) for r in _raw_rows(m.source)]
    assert len(ids) == len(set(ids)), "a source id listed twice"
    src_ids = set(src.ids or range(src.num_classes))
    assert src_ids <= set(ids) <= src_ids | set(src.ignore_ids), "every source class listed, nothing else"
    # the source names are the source taxonomy's class names (the ADE20K file adds MSeg's class in brackets)
    for r in _raw_rows(m.source):
        sid = int(r["source_id"])
        if sid in src_ids:
            want = src.names[(src.ids or range(src.num_classes)).index(sid)]
            assert r["source_name"].split(" (mseg: ")[0] == want
    assert (m.lut[list(src_ids)] != IGNORE).any()


def test_mseg_and_ade20k_correspondences():
    mseg, ade = load_taxonomy("mseg194"), load_taxonomy("ade20k150")
    m = load_mapping("mseg_universal_to_scannet20", SCANNET20)
    to = {n: SCANNET20.names[m.lut[i]] if m.lut[i] != IGNORE else None for i, n in enumerate(mseg.names)}
    assert to["chair_other"] == to["armchair"] == to["stool"] == "chair" and to["couch"] == "sofa"
    assert to["painting"] == "picture" and to["refrigerator"] == "refrigerator" and to["sky"] is None
    a = load_mapping("ade20k_to_scannet20", SCANNET20)
    to = {n: SCANNET20.names[a.lut[i]] if a.lut[i] != IGNORE else None for i, n in enumerate(ade.names)}
    assert to["windowpane"] == "window" and to["bookcase"] == "bookshelf" and to["screen door"] == "door"
    assert to["countertop"] == "counter" and to["computer"] is None and to["building"] is None
    assert set(SCANNET20.names) - {"shower curtain"} == {c for c in to.values() if c}  # ADE20K has no shower curtain


def test_mapping_target_must_be_the_runs_taxonomy(tmp_path):
    with pytest.raises(ValueError, match="targets taxonomy scannet20.*run's taxonomy is nyu40"):
        load_mapping("nyu40_to_scannet20", load_taxonomy("nyu40"))
    # a mapping to any taxonomy: names checked against it
    p = tmp_path / "mine_to_city.csv"
    p.write_text("# target: cityscapes19\nsource_id,source_name,target\n0,street,road\n1,auto,car\n2,x,ignore\n")
    m = load_mapping(p, load_taxonomy("cityscapes19"))
    np.testing.assert_array_equal(m.apply(np.array([1, 0, 2]))[0], [13, 0, IGNORE])
    p.write_text("source_id,source_name,target\n0,street,pavement\n")
    with pytest.raises(ValueError, match="unknown target class 'pavement' for taxonomy cityscapes19"):
        load_mapping(p, load_taxonomy("cityscapes19"))


def test_native_mapping_of_label_ids():
    nyu = native_mapping(load_taxonomy("nyu40"))
    np.testing.assert_array_equal(nyu.apply(np.array([[0, 1], [40, 24]]))[0], [[IGNORE, 0], [39, 23]])
    with pytest.raises(ValueError, match="41"):
        nyu.apply(np.array([41]))
    s200 = native_mapping(load_taxonomy("scannet200"))
    assert s200.apply(np.array([1191, 3]))[0].tolist() == [199, 2]
    with pytest.raises(ValueError, match="12"):  # 12 is no ScanNet200 class
        s200.apply(np.array([12]))
    assert native_mapping(SCANNET20) is None  # ids used as they are, as before


def test_taxonomy_from_csv(tmp_path):
    p = tmp_path / "lab.csv"
    p.write_text("# my lab's classes\n# name: lab\n# ignore: 0\nid,name\n3,shelf\n7,robot\n12,Box\n")
    tax = load_taxonomy(p)
    assert tax.name == "lab" and tax.names == ("shelf", "robot", "Box") and tax.ids == (3, 7, 12)
    assert (tax.colors == generated_colors(3)).all() and len({tuple(c) for c in tax.colors.tolist()}) == 3
    assert native_mapping(tax).apply(np.array([0, 12, 3]))[0].tolist() == [IGNORE, 2, 0]
    p.write_text("id,name,r,g,b\n0,a,1,2,3\n1,b,4,5,6\n")
    tax = load_taxonomy(str(p))
    assert tax.name == "lab" and tax.ids is None and tax.colors.tolist() == [[1, 2, 3], [4, 5, 6]]
    for text, msg in [("id,label\n0,a\n", "header"), ("id,name\n0,a\n1,A\n", "duplicate class name"),
                      ("id,name\n0,a\n0,b\n", "duplicate class id"), ("id,name,r,g,b\n0,a,1,2,300\n", "0..255"),
                      ("id,name\nx,a\n", "integers"), ("# ignore: 0\nid,name\n0,a\n", "also class ids")]:
        p.write_text(text)
        with pytest.raises(ValueError, match=msg):
            load_taxonomy(p)
    with pytest.raises(FileNotFoundError, match="no shipped taxonomy named 'nope'.*scannet20"):
        load_taxonomy("nope")


def test_taxonomy_from_yaml(tmp_path):
    p = tmp_path / "lab.yaml"
    p.write_text("name: lab\nignore: [255]\nclasses:\n  - {id: 0, name: floor, color: [10, 20, 30]}\n"
                 "  - {id: 5, name: pallet}\n")
    tax = load_taxonomy(p)
    assert tax.names == ("floor", "pallet") and tax.ids == (0, 5) and tax.ignore_ids == (255,)
    assert tax.colors[0].tolist() == [10, 20, 30]
    p.write_text("classes: {1: wall, 2: floor}\n")
    tax = load_taxonomy(p)
    assert tax.name == "lab" and tax.names == ("wall", "floor") and tax.ids == (1, 2)
    p.write_text("classes: 3\n")
    with pytest.raises(ValueError, match="'classes' must be"):
        load_taxonomy(p)


def test_taxonomy_config_keys():
    assert default_config().taxonomy.name == "scannet20"
    with pytest.raises(ConfigError, match="taxonomy.name='nope'"):
        default_config(**{"taxonomy.name": "nope"})
    with pytest.raises(ConfigError, match="taxonomy.path"):
        default_config(**{"taxonomy.name": "file"})
    cfg = default_config(**{"taxonomy.name": "cityscapes19"})
    assert resolve_taxonomy(cfg).num_classes == 19


def test_ids_taxonomy_from_prediction_images(tmp_path):
    for i, ids in enumerate(([[3, 3], [9, 130]], [[9, 0], [0, 3]], [[77, 77], [77, 77]])):
        Image.fromarray(np.array(ids, np.uint8)).save(tmp_path / f"view_{i:04d}.png")
    cfg = default_config(**{"taxonomy.name": "ids", "taxonomy.scan_frames": 2, "predictions.source": "files",
                            "predictions.folder": str(tmp_path), "predictions.mapping": None})
    with pytest.warns(UserWarning, match=r"taxonomy=ids: 4 classes class_<id>.*\[0, 3, 9, 130\].*2 prediction"):
        tax = resolve_taxonomy(cfg)
    assert tax.names == ("class_0", "class_3", "class_9", "class_130") and tax.ids == (0, 3, 9, 130)
    assert native_mapping(tax).apply(np.array([130, 0]))[0].tolist() == [3, 0]
    with pytest.raises(ValueError, match="77"):  # in the third image only: outside the scanned frames
        native_mapping(tax).apply(np.array([77]))
    with pytest.raises(ValueError, match="taxonomy=ids: no label images"):
        resolve_taxonomy(default_config(**{"taxonomy.name": "ids"}))  # the demo has no label files


@pytest.fixture(scope="module")
def scannet_dir(tmp_path_factory):
    return write_scannet(tmp_path_factory.mktemp("tax"), make_world())


def test_scannet_source_in_nyu40_and_ids(scannet_dir):
    from diffuser_lab.data.sources.scannet import load_scannet

    s20 = load_scannet(scannet_dir, frame_step=1, max_frames=2)
    nyu = load_scannet(scannet_dir, frame_step=1, max_frames=2, mapping=None, taxonomy=load_taxonomy("nyu40"))
    assert nyu.taxonomy.name == "nyu40"
    same = s20.gt_labels != IGNORE  # every ScanNet-20 class is one NYU40 class of the same name
    names20 = np.array(SCANNET20.names + ("-",))[s20.gt_labels[same]]
    names40 = np.array(nyu.taxonomy.names + ("-",))[nyu.gt_labels[same]]
    assert same.any() and (np.char.replace(names40, "refridgerator", "refrigerator") == names20).all()
    cfg = default_config(**{"scene.source": "scannet", "scene.options.root": str(scannet_dir),
                            "taxonomy.name": "ids"})
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        tax = resolve_taxonomy(cfg)
    assert any("label-filt" in str(x.message) and "labels.ply" in str(x.message) for x in w)
    raw = np.unique(np.concatenate([np.unique(np.asarray(Image.open(p))) for p in
                                    sorted((scannet_dir / "label-filt").glob("*.png"))[:10]]))
    assert set(raw.tolist()) <= set(tax.ids) and all(n == f"class_{i}" for n, i in zip(tax.names, tax.ids))
    ids_scene = load_scannet(scannet_dir, frame_step=1, max_frames=2, mapping=None, taxonomy=tax)
    back = np.array(tax.ids)[ids_scene.gt_labels]  # class index -> raw NYU40 id, as in the PLY
    from diffuser_lab.data.meshes import read_labelled_mesh

    np.testing.assert_array_equal(back, read_labelled_mesh(scannet_dir / "scene0999_00_vh_clean_2.labels.ply")[2])


def test_demo_relabelled_into_another_taxonomy(small_demo_scene):
    nyu = relabel_scene(small_demo_scene, load_taxonomy("nyu40"))
    assert nyu.taxonomy.name == "nyu40" and nyu.n_points == small_demo_scene.n_points
    a, b = small_demo_scene.gt_labels, nyu.gt_labels
    assert ((a == IGNORE) == (b == IGNORE)).all()
    assert (np.array(nyu.taxonomy.names)[b[b >= 0]][:50] != "").all()
    wall = SCANNET20.names.index("wall")
    assert (b[a == wall] == nyu.taxonomy.names.index("wall")).all()
    f0, g0 = small_demo_scene.frames[0].gt_labels, nyu.frames[0].gt_labels
    assert (g0[f0 == SCANNET20.names.index("floor")] == nyu.taxonomy.names.index("floor")).all()
    with pytest.raises(ValueError, match="no shipped mapping scannet20_to_cityscapes19"):
        relabel_scene(small_demo_scene, load_taxonomy("cityscapes19"))


@pytest.mark.slow
def test_cli_run_in_nyu40(tmp_path):
    import open3d as o3d

    run = tmp_path / "run"
    p = run_cli(*SMALL_DEMO, "taxonomy=nyu40", "record=mcap", "output.quiet=true", f"hydra.run.dir={run}")
    assert p.returncode == 0, p.stderr[-2000:]
    s = json.loads((run / "summary.json").read_text())
    assert s["taxonomy"] == "nyu40" and s["n_classes"] == 40
    per_class = set(s["metrics"]["per_class_iou"])
    assert {"wall", "floor"} <= per_class <= set(load_taxonomy("nyu40").names)
    labels = np.load(run / "labels.npy")
    cols = o3d.t.io.read_point_cloud(str(run / "labels.ply")).point.colors.numpy()
    cols = (cols * 255).round().astype(np.uint8) if cols.dtype.kind == "f" else cols
    tax = load_taxonomy("nyu40")
    ok = labels >= 0
    assert ok.mean() > 0.5 and labels.max() < 40
    np.testing.assert_array_equal(cols[ok], tax.colors[labels[ok]])
    from mcap.reader import make_reader

    with open(run / "run.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    info = next(m for m in meta.values() if "class_names" in m)
    assert info["taxonomy"] == "nyu40" and json.loads(info["class_names"]) == list(tax.names)
    assert json.loads(info["class_colors"]) == tax.colors.tolist()
    bad = run_cli("taxonomy=file", cwd=tmp_path)
    assert bad.returncode == 2 and "taxonomy.path" in bad.stderr


def test_plot_class_order_follows_the_runs_taxonomy(tmp_path):
    from analysis.plots import _class_order
    from diffuser_lab.runs.results import Run

    ious = {"pillow": 1.0, "floor": 2.0, "wall": 3.0, "zebra_thing": 4.0}
    runs = [Run(tmp_path, {"taxonomy": "nyu40", "metrics": {"per_class_iou": ious}})]
    assert _class_order(runs) == ["wall", "floor", "pillow", "zebra_thing"]  # NYU40 order, unknown last
    runs = [Run(tmp_path, {"taxonomy": "ids", "metrics": {"per_class_iou": ious}})]
    assert _class_order(runs) == list(ious)  # no shipped order: first seen


@pytest.mark.slow
def test_cli_ids_taxonomy_on_an_rgbd_folder(tmp_path):
    from datasets import write_label_predictions, write_rgbd

    world = make_world()
    root = write_rgbd(tmp_path, world)  # NYU40 ids in the label images, as a network's would be
    preds = write_label_predictions(tmp_path / "preds", world, [f"frame-{i:06d}" for i in range(len(world["poses"]))])
    run = tmp_path / "run"
    p = run_cli("scene=rgbd_folder", f"scene.options.root={root}", "scene.options.label_suffix=label.png",
                "predictions=files", f"predictions.folder={preds}", "predictions.mapping=null", "taxonomy=ids",
                "record=off",
                "output.quiet=true", "solver.max_iter=20", f"hydra.run.dir={run}", cwd=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "diffuser-lab: warning: taxonomy=ids:" in p.stderr and "label images" in p.stderr
    s = json.loads((run / "summary.json").read_text())
    files = sorted(root.glob("frame-*.label.png")) + sorted(preds.glob("*.png"))
    raw = np.unique(np.concatenate([np.unique(np.asarray(Image.open(f))) for f in files]))
    assert s["taxonomy"] == "ids" and s["n_classes"] == raw.size
    # no labelled cloud, so no 3D metrics; the 2D score holds the ids taxonomy: the "network" outputs the
    # truth (rendered at another resolution), so the same ids must land in the same classes on both sides
    p2d = s["predictions_2d"]
    assert set(p2d["per_class_iou"]) <= {f"class_{i}" for i in raw} and p2d["miou"] > 90
    assert (np.load(run / "labels.npy") >= 0).mean() > 0.5


def test_compare_colours_of_a_run_in_an_unshipped_taxonomy():
    import open3d as o3d

    from analysis.compare import _classes

    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.zeros((3, 3), np.float32)))
    pcd.point.colors = o3d.core.Tensor(np.array([[1, 2, 3], [4, 5, 6], [1, 2, 3]], np.uint8))
    names, colors = _classes({"taxonomy": "warehouse", "n_classes": 3}, pcd, np.array([2, 0, 2]))
    assert names == ("class_0", "class_1", "class_2") and colors[[2, 0]].tolist() == [[1, 2, 3], [4, 5, 6]]
    names, colors = _classes({"taxonomy": "nyu40"}, pcd, np.array([2, 0, 2]))
    assert names == load_taxonomy("nyu40").names
