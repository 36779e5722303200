"""diffuser-lab's Hydra sweeper (``hydra/sweeper=diffuser_lab``, the default of conf/config.yaml).

Hydra finds plugins only in the ``hydra_plugins`` namespace package, hence this folder beside
``diffuser_lab/`` (the wheel carries both)."""
