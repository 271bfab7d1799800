"""`roadmap eval`: the evaluation suite. Many full pipeline runs (`roadmap demo`: a mapping fleet,
shards, compressed tiles and a separate production car) over worlds and seeds, each scored
against the simulator's ground truth, and one summary of the distribution (DIR/eval.json and
DIR/eval.png). The services never read the truth; only this harness and the demo's report do."""
