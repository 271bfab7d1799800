"""The files `roadmap localize` writes in its OUT, and their readers. Nothing in them comes from
truth; the evaluation harness (services/eval/localization.py) reads them with the drive log.

    trajectory.tum     the estimate of every frame that has one (TUM: `t x y z qx qy qz qw`,
                       common/trajectory.py)
    diagnostics.jsonl  one JSON object per frame, in frame order: i (frame index in the drive
                       log), t_ns, ok (integrity), pose [x, y, yaw] (world ENU, m / rad, full
                       precision; null before initialization), cov (3x3 of the pose), sigma_xy_m,
                       then the localizer's own diagnostics of the frame (state, icp, points,
                       inliers, rmse_m, ...)
    tiles.npz          every tile message the car applied, in order: frame (index of the frame
                       it arrived for), tile (tx, ty), version, codec, and the payloads as one
                       byte blob with offsets (message k = blob[offsets[k]:offsets[k + 1]])
    summary.json       map codec, segmenter, initializations, tiles fetched, tile bytes and
                       updates, per-frame timings (p50 / p95 ms)
    config.toml        the effective config"""

import json
import math
from pathlib import Path

import numpy as np

from common.messages import Tile


def diag_row(i: int, est) -> dict:
    """One line of diagnostics.jsonl for the estimate of frame i."""
    finite = bool(np.all(np.isfinite(est.pose)))
    cov = np.asarray(est.cov, dtype=float)
    row = {
        "i": int(i),
        "t_ns": int(est.t_ns),
        "ok": bool(est.ok),
        "pose": [float(v) for v in est.pose] if finite else None,
        "cov": cov.tolist() if np.all(np.isfinite(cov)) else None,
        "sigma_xy_m": [round(float(math.sqrt(max(est.cov[k, k], 0.0))), 4) for k in (0, 1)],
    }
    row.update(est.diag)
    return row


def write_summary(out: Path, summary: dict) -> None:
    (out / "summary.json").write_text(json.dumps(summary, indent=1))


def read_summary(out: Path) -> dict:
    return json.loads((Path(out) / "summary.json").read_text())


def read_diagnostics(path: Path) -> list[dict]:
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


class TileLog:
    """The tile messages the car applied, with the frame each arrived for (-> tiles.npz)."""

    def __init__(self):
        self.frame = 0  # the frame being prepared: tiles stored now arrive for it
        self.received: list[tuple[int, Tile]] = []

    def add(self, msg: Tile) -> None:
        self.received.append((self.frame, msg))

    def save(self, path: Path) -> None:
        blobs = [bytes(m.data) for _, m in self.received]
        np.savez(
            path,
            frame=np.array([f for f, _ in self.received], np.int64),
            tile=np.array([m.tile for _, m in self.received], np.int64).reshape(-1, 2),
            version=np.array([m.version for _, m in self.received], np.int64),
            codec=np.array([m.codec for _, m in self.received], dtype=str),
            blob=np.frombuffer(b"".join(blobs), np.uint8),
            offsets=np.cumsum([0] + [len(b) for b in blobs]).astype(np.int64),
        )


def read_tiles(path: Path) -> list[tuple[int, Tile]]:
    """tiles.npz -> [(frame, Tile)] in the order the car applied them."""
    with np.load(path) as z:
        blob, off = z["blob"].tobytes(), z["offsets"]
        return [
            (int(z["frame"][k]),
             Tile((int(t[0]), int(t[1])), int(z["version"][k]), str(z["codec"][k]),
                  blob[off[k] : off[k + 1]]))
            for k, t in enumerate(z["tile"])
        ]
