"""The paper's method: pixel-to-point evidence (Eqs. 1-2, 11-13), the kNN graph (Eqs. 3-4), the
reduced diffusion with its early stop and labels (Eqs. 10, 14-16), the metrics, and a straightforward
scipy float64 reference of the whole core (reference.py)."""
