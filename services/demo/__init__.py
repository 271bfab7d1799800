"""The local fleet: `roadmap demo` / `roadmap up` (run.py), `roadmap bench` (bench.py), the
process supervisor (procs.py), Zenoh queries in a child process (fetch.py), the evaluation and
figures of report.json, and the container healthcheck (health.py)."""
