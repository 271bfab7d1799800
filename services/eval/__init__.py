"""The evaluation harness: accuracy against the truth that only the simulator knows (true poses
in the drive logs, the world's ground-truth raster), kept out of the product services.

localization: the report's localization section (errors, availability, convergence); mapping: a
vehicle's local map vs the world; map: the merged map vs the world (report.json's map section,
the repaint check); comma2k19: the pose graph on a real drive vs its reference poses."""
