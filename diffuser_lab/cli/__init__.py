"""The console scripts: diffuser-lab (main.py, the Hydra command line), diffuser-lab-inspect
(inspect.py), diffuser-lab-bench (bench.py), diffuser-lab-depth-report (depth_report.py) and
diffuser-lab-query (query.py: a features run relabelled with words)."""
