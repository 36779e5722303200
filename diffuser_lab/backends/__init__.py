"""The hot loops behind the method: numba kernels (numba/: grid kNN, Eq. 4 weights, Jacobi steps,
fused evidence) and torch for CUDA (torch.py). Without numba (or with DIFFUSER_LAB_NUMBA=0) the
method runs on numpy/scipy."""
