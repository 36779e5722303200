"""One run and the protocols around it: the pipeline (load -> evidence + graph -> diffusion ->
labels -> metrics), the single-frame protocol, the summary and records a run writes, the
benchmark workloads, and sweeps (launchers, job lines, the collected table)."""
