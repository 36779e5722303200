"""diffuser-lab: multi-view 2D-to-3D semantic label diffusion (Mascaro et al., ICRA 2021)."""

__version__ = "0.1.0"
