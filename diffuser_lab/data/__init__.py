"""What a run reads: the scene (points, normals, ground truth) and its frames (intrinsics, world-to-camera
pose, metric depth, 2D labels or class probabilities), from a source (sources/), rendered views,
simulated or file predictions, class mappings (mappings/) and the input checks."""
