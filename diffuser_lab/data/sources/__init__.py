"""Scene sources: the demo room (demo.py), views rendered from a labelled mesh (mesh_views.py), a
ScanNet export (scannet.py), a posed RGB-D folder (rgbd_folder.py), a TUM RGB-D sequence (tum.py)."""
