"""Files a run writes (diffuser_lab/runs/records.py): output.clouds writes the labelled cloud as LAS,
LAZ and a ROS 2 bag beside labels.npy, each read back equal."""
import numpy as np

from diffuser_lab.config import CloudFormat
from diffuser_lab.data.clouds import read_cloud
from diffuser_lab.data.scene import SCANNET20
from diffuser_lab.data.clouds import read_pointcloud2_bag
from diffuser_lab.runs.records import CLOUD_WRITERS, write_labels


def test_output_clouds_read_back(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 4, (300, 3)).astype(np.float32)
    lab = rng.integers(-1, 20, 300).astype(np.int16)
    files = write_labels(tmp_path, pts, lab, SCANNET20, ply=False, clouds=list(CloudFormat))
    assert set(CLOUD_WRITERS) == {c.value for c in CloudFormat}  # every format the config offers has a writer
    assert files == {"labels": "labels.npy", "labels_las": "labels.las", "labels_laz": "labels.laz",
                     "labels_ros2": "labels_ros2/labels_ros2.mcap"}
    for name in ("labels.las", "labels.laz"):  # loop over the two LAS encodings
        back = read_cloud(tmp_path / name)
        assert np.abs(back["points"] - pts).max() < 1e-3 and (back["labels"] == lab).all()
    p, labels, colors, frame = read_pointcloud2_bag(tmp_path / "labels_ros2")
    assert np.abs(p - pts).max() == 0 and (labels == lab).all() and frame == "map"
    assert (colors[lab >= 0] == SCANNET20.colorize(lab)[lab >= 0]).all()
