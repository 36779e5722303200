"""GPU backend (``solver.backend=torch``, optional extra ``gpu``): Eq. 10 on CUDA with PyTorch.

Same contract as :func:`diffuser_lab.diffusion.diffuse`: the same floors and scaling, the same
stopping rule, observers called exactly as on the CPU (Z copied back to the host in the paper's
units only for the iterations an observer wants), and a float32 Z in the caller's point order.
P is a CUDA CSR tensor in the graph's Morton order; each step is one sparse-dense product
(cuSPARSE SpMM) plus a few element-wise kernels. Without CUDA it stops with a one-line error.
"""
from __future__ import annotations

from typing import Optional

import numpy as np


def cuda_available() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def _torch(device: Optional[str] = None):
    try:
        import torch
    except ImportError:
        raise RuntimeError("solver.backend=torch: PyTorch is not installed (pip install 'diffuser-lab[gpu]')") from None
    if device is None and not torch.cuda.is_available():
        raise RuntimeError("solver.backend=torch: no CUDA GPU is available (torch.cuda.is_available() is False)")
    return torch


def diffuse_torch(system, *, max_iter: int = 200, tol: float = 1e-4, observer=None, device: Optional[str] = None):
    """:func:`~diffuser_lab.diffusion.diffuse` on a CUDA device (see module doc)."""
    from . import progress
    from .diffusion import SCORE_FLOOR, DiffusionResult, iteration_inputs, observes, show

    torch = _torch(device)  # device="cpu" runs the same code without a GPU (tests)
    dev = torch.device(device or "cuda")
    active, full_shape, scale, order, (indptr, indices, data), B_src = iteration_inputs(system)
    n = full_shape[0]
    Pt = torch.sparse_csr_tensor(torch.from_numpy(np.asarray(indptr, np.int64)),
                                 torch.from_numpy(np.asarray(indices, np.int64)),
                                 torch.from_numpy(np.asarray(data, np.float32)), size=(n, n)).to(dev)
    B = torch.from_numpy(np.ascontiguousarray(B_src[:, active] / scale, np.float32)).to(dev)
    Z = torch.zeros_like(B)
    floor = float(SCORE_FLOOR)
    order_t = None if order is None else torch.from_numpy(order).to(dev)

    def paper_units(Zs) -> np.ndarray:
        out = np.zeros(full_shape, np.float32)
        z = Zs * float(scale)
        if order_t is not None:
            zz = torch.empty_like(z)
            zz[order_t] = z
            z = zz
        out[:, active] = z.cpu().numpy()
        return out

    residuals: list[float] = []
    converged = False
    it = 0
    with progress.stage(f"diffusion (jacobi, torch {dev}, {n:,} points)", total=max_iter, unit="it") as bar:
        for it in range(1, max_iter + 1):
            Zn = torch.sparse.mm(Pt, Z) if Z.shape[1] else Z.clone()
            Zn += B
            Zn = torch.where(Zn >= floor, Zn, torch.zeros((), device=dev, dtype=Zn.dtype))
            if Zn.numel():
                top, change = torch.stack([Zn.max(), (Zn - Z).abs().max()]).tolist()
            else:
                top = change = 0.0
            residual = change / top if top > 0 else 0.0
            residuals.append(residual)
            Z = Zn
            if observes(observer, it):
                show(observer, it, paper_units(Z), residual)
            if bar.enabled:
                bar.note(f"{'converged, ' if residual <= tol else ''}residual {residual:.1e}")
                bar.update()
            if residual <= tol:
                converged = True
                break
    return DiffusionResult(Z=paper_units(Z), iterations=it, converged=converged,
                           residual=residuals[-1] if residuals else 0.0, residuals=residuals,
                           info={"solver": "jacobi", "backend": "torch", "device": str(dev)})
