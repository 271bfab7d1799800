"""The evaluation harness: accuracy of what the services output, against the truth that only the
simulator knows (true poses in the drive logs, the world's ground-truth raster).

The services never read truth. Each module here computes the report.json section of its name
from their outputs: localization (the localizer's diagnostics.jsonl and tiles.npz vs the drive
log's true poses), mapping (a mapping vehicle's poses.npz and local map vs truth), map (the
merged tiles vs the world); comma2k19: the pose graph on a real drive vs its reference poses.

`roadmap eval` (command.py, run.py, suite.py, score.py, summary.py, figure.py) runs many full
pipeline runs (`roadmap demo`: a mapping fleet, shards, compressed tiles and a separate
production car) over worlds and seeds, scores each against the truth (score.py) and writes one
summary of the distribution (DIR/eval.json and DIR/eval.png)."""
