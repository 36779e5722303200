import subprocess
import sys

CHECK = """
import sys
from diffuser_lab.data.o3d import open3d
o3d = open3d()
assert "dash" not in sys.modules and "plotly" not in sys.modules, "the plotly viewer was imported"
import numpy as np
pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.eye(3)))
fig = o3d.visualization.get_plotly_fig([pcd])  # the stand-in imports the real viewer and calls it
assert type(fig).__name__ == "Figure" and "dash" in sys.modules
assert o3d.visualization.draw_plotly.__module__ == "open3d.visualization.draw_plotly"
"""


def test_open3d_without_its_plotly_viewer_until_a_user_calls_it():
    p = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
