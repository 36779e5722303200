"""Scripts that compare diffuser-lab runs: collect, plots, compare, report.

Run them as ``python -m analysis.collect ...`` from the repository root, or as scripts.
"""
