"""GPU backend (``solver.backend=torch``, optional extra ``gpu``): steps of Eq. 10 on CUDA with PyTorch.

Behind :class:`~diffuser_lab.backends.base.JacobiBackend`: the same floors, scaling and stopping
rule as the CPU backends, Z copied back to the host in the paper's units only for the iterations
an observer wants. P is a CUDA CSR tensor in the graph's Morton order; each step is one
sparse-dense product (cuSPARSE SpMM) plus a few element-wise kernels (a step's residual is read
back to the host, as every backend reports each step's). Without CUDA it stops with one line.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from .base import IterationInputs, JacobiBackend


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


class TorchJacobi(JacobiBackend):
    """Jacobi steps on a CUDA device (``device="cpu"`` runs the same code without a GPU, for tests)."""

    name = "torch"

    def __init__(self, inputs: IterationInputs, tol: float, rows_hint: int = 0, device: Optional[str] = None):
        self.torch = _torch(device)
        self.device = self.torch.device(device or "cuda")
        super().__init__(inputs, tol, rows_hint)

    def setup(self, inputs: IterationInputs) -> None:
        super().setup(inputs)
        torch, dev = self.torch, self.device
        n = inputs.shape[0]
        self.P = torch.sparse_csr_tensor(torch.from_numpy(np.asarray(inputs.indptr, np.int64)),
                                         torch.from_numpy(np.asarray(inputs.indices, np.int64)),
                                         torch.from_numpy(np.asarray(inputs.data, np.float32)), size=(n, n)).to(dev)
        self.B = torch.from_numpy(np.ascontiguousarray(inputs.B[:, inputs.active] / inputs.scale, np.float32)).to(dev)
        self.Z = torch.zeros_like(self.B)
        self.order = None if inputs.order is None else torch.from_numpy(inputs.order).to(dev)

    def state(self) -> np.ndarray:
        return self.Z.cpu().numpy()

    def load(self, Z: np.ndarray) -> None:
        self.Z = self.torch.from_numpy(np.ascontiguousarray(Z, np.float32)).to(self.device).reshape(self.B.shape)

    def details(self) -> dict:
        return {"backend": self.name, "device": str(self.device)}

    def step(self) -> tuple[float, float]:
        torch, Z = self.torch, self.Z
        Zn = torch.sparse.mm(self.P, Z) if Z.shape[1] else Z.clone()
        Zn += self.B
        Zn = torch.where(Zn >= float(self.inputs.floor), Zn, torch.zeros((), device=self.device, dtype=Zn.dtype))
        top, change = torch.stack([Zn.max(), (Zn - Z).abs().max()]).tolist() if Zn.numel() else (0.0, 0.0)
        self.Z = Zn
        return change, top

    def paper_units(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        inp = self.inputs
        Z_full = np.zeros(inp.shape, np.float32) if out is None else out
        z = self.Z * float(inp.scale)
        if self.order is not None:
            zz = self.torch.empty_like(z)
            zz[self.order] = z
            z = zz
        Z_full[:, inp.active] = z.cpu().numpy()
        return Z_full
