"""The local fleet: `roadmap demo` / `roadmap up` (run.py: the orchestration as named steps),
report.json assembled from the services' outputs and the truth (report.py; the metrics are
services/eval's), its figures (figures.py), the process supervisor (procs.py), Zenoh queries in a
child process (fetch.py), and the container healthcheck (health.py)."""
