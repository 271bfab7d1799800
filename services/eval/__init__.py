"""The evaluation harness: accuracy of what the services output, against the truth that only the
simulator knows (true poses in the drive logs, the world's ground-truth raster).

The services never read truth. Each module here computes the report.json section of its name
from their outputs: localization (the localizer's diagnostics.jsonl and tiles.npz vs the drive
log's true poses), mapping (a mapping vehicle's poses.npz and local map vs truth), map (the
merged tiles vs the world); comma2k19: the pose graph on a real drive vs its reference poses."""
