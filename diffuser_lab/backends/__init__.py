"""The hot loops behind the method: numba kernels (numba/: grid kNN, Eq. 4 weights, Jacobi steps,
fused evidence) and torch for CUDA (torch.py). Without numba (or with DIFFUSER_LAB_NUMBA=0) the
method runs on numpy/scipy; knn.py, growing.py and voxel_map.py choose between the kernels and
their numpy/scipy twins for the kNN graph, the growing map's graph and its voxel map."""
