"""One run and the protocols around it: the registry of protocols (protocols.py) and the three it
ships: global 3D labelling (pipeline.py: load -> evidence + graph -> diffusion -> labels ->
metrics), the single-frame protocol (single_frame.py) and the online one (online.py); the resolve
step of a config (resolve.py), the summary and records a run writes, the benchmark workloads, and
sweeps (launchers, job lines, the collected table)."""
