"""External-model proof: the real pretrained TwinLiteNet through our OnnxSegmenter on real frames.

TwinLiteNet (MIT; ../shared/data/models/twinlitenet) has two heads, `da` (drivable area) and `ll`
(lane line), each 2-class logits at 640x360 from RGB / 255. We map da:1 -> ROAD and ll:1 ->
LANE_LINE (lane lines paint over road), project the lane-line pixels to the ground with a
plausible calibration (paper eq. 1, `CameraModel.ground_points`) and save pictures of both.

    python -m training.external --out OUT [--data ../shared/data]
"""

import argparse
import json
import logging
import time
from pathlib import Path

import cv2
import numpy as np

from common.camera import CameraModel
from common.classes import Cls, colorize
from common.segmentation import OnnxSegmenter

logger = logging.getLogger(__name__)

TWINLITE_HEADS = {"da": {1: int(Cls.ROAD)}, "ll": {1: int(Cls.LANE_LINE)}}
TWINLITE_PRIORITY = ["da", "ll"]
BEV_RANGE_M = (0.0, 40.0, -10.0, 10.0)  # x_min, x_max, y_min, y_max in the vehicle frame
BEV_PX_PER_M = 12
COMMA_PITCH_DEG = 3.0  # looking down; from the vanishing point of preview.png's lane lines


def twinlitenet_segmenter(data_dir: Path, threads: int = 2) -> OnnxSegmenter:
    return OnnxSegmenter(
        data_dir / "models" / "twinlitenet" / "twinlitenet.onnx", input_size=(640, 360),
        scale=1.0 / 255.0, mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0), head_map=TWINLITE_HEADS,
        priority=TWINLITE_PRIORITY, intra_op_threads=threads, name="twinlitenet",
    )


def assumed_camera(name: str, width: int, height: int) -> CameraModel:
    """A plausible calibration: comma2k19's published intrinsics; a generic dash cam otherwise.

    Heights are assumed: 1.2 m (comma) and 1.4 m (BDD dash cams: no calibration given, fx guessed
    from a ~65 deg horizontal field of view, level). The comma pitch comes from the lane lines'
    vanishing point in preview.png (v ~ 388 px above cy = 437 px: the camera looks ~3 deg down)."""
    if name.startswith("comma2k19"):
        return CameraModel.from_mount(width=width, height=height, fx=910.0, fy=910.0, cx=582.0,
                                      cy=437.0, dist=[0, 0, 0, 0], x_m=1.5, y_m=0.0, height_m=1.2,
                                      pitch_deg=COMMA_PITCH_DEG)
    f = 0.5 * width / np.tan(np.radians(65.0) / 2)
    return CameraModel.from_mount(width=width, height=height, fx=f, fy=f, cx=width / 2,
                                  cy=height / 2, dist=[0, 0, 0, 0], x_m=1.5, y_m=0.0,
                                  height_m=1.4, pitch_deg=0.0)


def real_frames(data_dir: Path) -> list[tuple[str, Path]]:
    frames = [(p.stem, p) for p in sorted((data_dir / "images").glob("*.jpg"))]
    comma = data_dir / "comma2k19" / "segment40" / "preview.png"
    if comma.is_file():
        frames.append(("comma2k19-segment40", comma))
    return frames


def read_rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(path)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def lane_ground_points(labels: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Lane-line pixels -> ground points (K, 2) in the vehicle frame (x fwd, y left), finite
    only."""
    v, u = np.nonzero(labels == Cls.LANE_LINE)
    uv = np.stack([u + 0.5, v + 0.5], axis=1).astype(np.float64)
    xy = camera.ground_points(uv) if len(uv) else np.zeros((0, 2))
    return xy[np.isfinite(xy).all(axis=1)]


def overlay(rgb: np.ndarray, labels: np.ndarray) -> np.ndarray:
    out = rgb.copy()
    paint = labels > 0
    out[paint] = (0.5 * rgb[paint] + 0.5 * colorize(labels)[paint]).astype(np.uint8)
    lane = labels == Cls.LANE_LINE
    out[lane] = (255, 40, 40)
    return out


def bev_image(points_xy_m: np.ndarray) -> np.ndarray:
    """Top view of ground points: x forward is up, y left is left; a 5 m grid."""
    x0, x1, y0, y1 = BEV_RANGE_M
    h, w = int((x1 - x0) * BEV_PX_PER_M), int((y1 - y0) * BEV_PX_PER_M)
    img = np.full((h, w, 3), 30, np.uint8)
    for xm in np.arange(x0, x1 + 1e-6, 5.0):
        r = int(h - (xm - x0) * BEV_PX_PER_M)
        cv2.line(img, (0, r), (w, r), (70, 70, 70), 1)
        cv2.putText(img, f"{xm:.0f} m", (2, max(r - 2, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    (150, 150, 150), 1)
    for ym in np.arange(y0, y1 + 1e-6, 5.0):
        c = int(w - (ym - y0) * BEV_PX_PER_M)
        cv2.line(img, (c, 0), (c, h), (70, 70, 70), 1)
    keep = (points_xy_m[:, 0] >= x0) & (points_xy_m[:, 0] < x1) & (points_xy_m[:, 1] >= y0) & (
        points_xy_m[:, 1] < y1)
    p = points_xy_m[keep]
    rows = (h - 1 - (p[:, 0] - x0) * BEV_PX_PER_M).astype(int)
    cols = (w - 1 - (p[:, 1] - y0) * BEV_PX_PER_M).astype(int)
    img[np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)] = (255, 255, 255)
    cv2.circle(img, (w // 2, h - 1), 5, (255, 80, 80), -1)  # the camera's foot point
    return img


def run_external(data_dir: Path, out_dir: Path, threads: int = 2) -> dict:
    """Segment every real frame, save mask + ground-point pictures, return a summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    seg = twinlitenet_segmenter(data_dir, threads)
    summary = {}
    for name, path in real_frames(data_dir):
        rgb = read_rgb(path)
        t0 = time.perf_counter()
        labels = seg.segment(rgb)
        ms = (time.perf_counter() - t0) * 1e3
        camera = assumed_camera(name, rgb.shape[1], rgb.shape[0])
        ground = lane_ground_points(labels, camera)
        _save(out_dir / f"{name}_mask.png", overlay(rgb, labels))
        _save(out_dir / f"{name}_ground.png", bev_image(ground))
        lane = labels == Cls.LANE_LINE
        summary[name] = {
            "ms": round(ms, 1),
            "lane_pixels": int(lane.sum()),
            "lane_pixels_lower_half": int(lane[lane.shape[0] // 2:].sum()),
            "road_fraction": float((labels == Cls.ROAD).mean()),
            "ground_points": int(len(ground)),
            "ground_lateral_m_p5_p95": _pct(ground[:, 1] if len(ground) else None),
            "ground_forward_m_p5_p95": _pct(ground[:, 0] if len(ground) else None),
        }
        logger.info("%s: %s", name, summary[name])
    (out_dir / "external.json").write_text(json.dumps(summary, indent=2))
    return summary


def _pct(values):
    if values is None:
        return None
    return [round(float(np.percentile(values, 5)), 2), round(float(np.percentile(values, 95)), 2)]


def _save(path: Path, rgb: np.ndarray) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def main(argv=None) -> int:
    from common.log import configure_logging

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    from services.sim.worlds import shared_data_dir

    parser.add_argument("--data", default=str(shared_data_dir()),
                        help="the shared data folder (default: $ROADMAP_SHARED_DATA, "
                        "else ../shared/data)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    configure_logging("INFO")
    run_external(Path(args.data), Path(args.out), args.threads)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
