"""The benchmarks behind `roadmap bench` (each module's `run(quick) -> dict`), the held-out
segmentation evaluation they share, and the paired comparison of two localizer settings."""
