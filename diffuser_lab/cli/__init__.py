"""The console scripts: diffuser-lab (main.py, the Hydra command line), diffuser-lab-inspect
(inspect.py) and diffuser-lab-bench (bench.py)."""
