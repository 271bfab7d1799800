"""The lab's rendering cost: seconds per training chunk of each of train-seg's two renderers
(training/synth.py's and the simulator's), n of each, and ms per frame. Writes JSON.

    python -m training.bench.render_chunks [--chunks 3] [--out render_chunks.json]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from training import data as seg_data


def training_chunks(n: int) -> dict:
    """Seconds per training chunk (CHUNK_FRAMES frames of one procedural town at 640 x 360,
    rendered as `roadmap train-seg` renders them, seed 0) of synth.py's chunks and of the
    simulator's, n of each (their median), and ms per frame."""
    out = {}
    for name, is_synth in (("synth", True), ("simulator", False)):
        ks = [k for k in range(10 * n) if seg_data.is_synth_chunk(k) == is_synth][:n]
        seconds = []
        for k in ks:
            t0 = time.perf_counter()
            seg_data._render_chunk((0, k, (640, 360), True, seg_data.TURN_PROB,
                                    seg_data.SYNTH_SHARE, "light"))
            seconds.append(time.perf_counter() - t0)
        median = float(np.median(seconds))
        out[name] = {"chunk_s": round(median, 2), "chunks": len(ks),
                     "ms_per_frame": round(1000 * median / seg_data.CHUNK_FRAMES, 1)}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--chunks", type=int, default=3)
    ap.add_argument("--out", default="render_chunks.json")
    args = ap.parse_args()
    report = training_chunks(args.chunks)
    Path(args.out).write_text(json.dumps(report, indent=1))
    sys.stdout.write(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
