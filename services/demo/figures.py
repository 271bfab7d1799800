"""The demo's figures, drawn with OpenCV and numpy (matplotlib is not a dependency).

Maps use the paper's palette (common.classes.colorize), north up; the trajectory is coloured by
its position error; error histograms follow the paper's figure 9; the repaint strip its figure 8."""

from pathlib import Path

import cv2
import numpy as np

from common.classes import colorize
from common.world import render_png

WHITE, GREY, BLACK = (255, 255, 255), (150, 150, 150), (0, 0, 0)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def map_figures(raw: np.ndarray, decoded: np.ndarray, truth: np.ndarray, out: Path) -> None:
    """OUT/map.png, map_truth.png and compression.png (merged vs decoded vs truth)."""
    save_map(raw, out / "map.png")
    save_map(truth, out / "map_truth.png")
    side_by_side([("merged map (before compression)", raw),
                  ("decoded from contours (after)", decoded),
                  ("ground truth", truth)], out / "compression.png")


def trajectory_figures(raw: np.ndarray, to_cells, track, out: Path) -> None:
    """OUT/trajectory.png (estimates on the map, coloured by position error) and errors.png
    (histograms of the scored estimates). track: services.demo.report.Track."""
    trajectory_by_error(raw, to_cells, track.truth_xy, track.est_xy, track.errors["position_m"],
                        out / "trajectory.png")
    error_histograms({k: v[track.scored] for k, v in track.errors.items()}, out / "errors.png")


def save_map(labels: np.ndarray, path) -> None:
    render_png(labels, str(path))


def _bgr(labels: np.ndarray) -> np.ndarray:
    """Label raster (row = north) -> BGR image, north up."""
    return cv2.cvtColor(colorize(labels[::-1]), cv2.COLOR_RGB2BGR)


def _title(img: np.ndarray, text: str) -> np.ndarray:
    bar = np.zeros((34, img.shape[1], 3), np.uint8)
    cv2.putText(bar, text, (8, 24), FONT, 0.7, WHITE, 1, cv2.LINE_AA)
    return np.vstack([bar, img])


def densest_window(labels: np.ndarray, rows: int, cols: int) -> tuple[int, int]:
    """(r0, c0) of the window holding the most marking cells (rows grow north)."""
    marks = (labels >= 2).astype(np.float32)
    if labels.shape[0] <= rows and labels.shape[1] <= cols:
        return 0, 0
    box = cv2.boxFilter(marks, -1, (min(cols, labels.shape[1]), min(rows, labels.shape[0])),
                        normalize=False, borderType=cv2.BORDER_CONSTANT)
    r, c = np.unravel_index(int(np.argmax(box)), box.shape)
    r0 = int(np.clip(r - rows // 2, 0, max(0, labels.shape[0] - rows)))
    c0 = int(np.clip(c - cols // 2, 0, max(0, labels.shape[1] - cols)))
    return r0, c0


def side_by_side(panels: list[tuple[str, np.ndarray]], path, window=(300, 500), scale=2) -> None:
    """Same window of several label rasters next to each other (e.g. raw vs decoded)."""
    r0, c0 = densest_window(panels[0][1], *window)
    tiles = []
    for title, labels in panels:
        crop = labels[r0 : r0 + window[0], c0 : c0 + window[1]]
        img = cv2.resize(_bgr(crop), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        tiles.append(_title(img, title))
    gap = np.full((tiles[0].shape[0], 6, 3), 255, np.uint8)
    out = tiles[0]
    for t in tiles[1:]:
        out = np.hstack([out, gap, t])
    cv2.imwrite(str(path), out)


def trajectory_by_error(labels: np.ndarray, to_cells, truth_xy: np.ndarray, est_xy: np.ndarray,
                        err_m: np.ndarray, path, max_err_m: float = 0.5,
                        margin_m: float = 15.0) -> None:
    """Map (dimmed) with the true path (grey) and the estimates coloured by error (JET, 0 to
    max_err_m). `to_cells` maps world (N, 2) -> mosaic (col, row)."""
    pts = np.vstack([truth_xy, est_xy])
    lo = np.floor(to_cells(pts.min(axis=0) - margin_m)).astype(int)
    hi = np.ceil(to_cells(pts.max(axis=0) + margin_m)).astype(int)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [labels.shape[1], labels.shape[0]])
    crop = labels[lo[1] : hi[1], lo[0] : hi[0]]
    img = (_bgr(crop).astype(np.float32) * 0.6).astype(np.uint8)
    h = crop.shape[0]

    def px(xy):
        cr = to_cells(xy) - lo
        return np.stack([cr[:, 0], h - 1 - cr[:, 1]], axis=1).round().astype(np.int32)

    cv2.polylines(img, [px(truth_xy)], False, GREY, 1, cv2.LINE_AA)
    colors = cv2.applyColorMap(
        (np.clip(err_m / max_err_m, 0, 1) * 255).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_JET
    ).reshape(-1, 3)
    for (u, v), col in zip(px(est_xy), colors, strict=True):
        cv2.circle(img, (int(u), int(v)), 3, tuple(int(c) for c in col), -1, cv2.LINE_AA)
    img = _colorbar(img, max_err_m)
    s = min(1.0, 2400 / max(img.shape[:2]))
    if s < 1.0:
        img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(path), img)


def _colorbar(img: np.ndarray, max_err_m: float) -> np.ndarray:
    bar = np.zeros((44, img.shape[1], 3), np.uint8)
    w = min(300, img.shape[1] - 120)
    ramp = cv2.applyColorMap(np.linspace(0, 255, max(w, 2)).astype(np.uint8).reshape(1, -1),
                             cv2.COLORMAP_JET)
    bar[8:24, 10 : 10 + ramp.shape[1]] = ramp[0]
    cv2.putText(bar, "0", (10, 40), FONT, 0.45, WHITE, 1, cv2.LINE_AA)
    cv2.putText(bar, f"{max_err_m:.1f} m position error", (max(10, w - 60), 40), FONT, 0.45,
                WHITE, 1, cv2.LINE_AA)
    return np.vstack([img, bar])


def error_histograms(errors: dict[str, np.ndarray], path, bins: int = 30) -> None:
    """Figure 9 style: one histogram per error (absolute values) with mean and p90 marked."""
    panels = []
    for name, unit in (("x_m", "m"), ("y_m", "m"), ("yaw_deg", "deg")):
        panels.append(_histogram(np.abs(errors[name]), f"{name.split('_')[0]} error [{unit}]",
                                 bins))
    cv2.imwrite(str(path), np.hstack(panels))


def _histogram(values: np.ndarray, title: str, bins: int, w: int = 420, h: int = 300):
    img = np.full((h, w, 3), 255, np.uint8)
    values = values[np.isfinite(values)]
    x0, y0, x1, y1 = 45, 30, w - 15, h - 40  # plot box
    cv2.putText(img, title, (x0, 20), FONT, 0.5, BLACK, 1, cv2.LINE_AA)
    cv2.rectangle(img, (x0, y0), (x1, y1), BLACK, 1)
    if values.size == 0:
        return img
    top = float(np.percentile(values, 99)) * 1.1 or 1e-3
    counts, edges = np.histogram(np.clip(values, 0, top), bins=bins, range=(0, top))
    frac = counts / counts.sum()
    bw = (x1 - x0) / bins
    for i, f in enumerate(frac):
        bh = int((y1 - y0) * f / max(frac.max(), 1e-9))
        cv2.rectangle(img, (int(x0 + i * bw) + 1, y1 - bh), (int(x0 + (i + 1) * bw) - 1, y1),
                      (200, 120, 40), -1)
    for val, label, col in ((values.mean(), "mean", (0, 0, 200)),
                            (np.percentile(values, 90), "p90", (0, 140, 0))):
        u = int(x0 + (x1 - x0) * min(val / top, 1.0))
        cv2.line(img, (u, y0), (u, y1), col, 1)
        at = (min(u + 3, x1 - 90), y0 + (14 if label == "mean" else 30))
        cv2.putText(img, f"{label} {val:.3f}", at, FONT, 0.4, col, 1, cv2.LINE_AA)
    for k in range(5):
        v = top * k / 4
        u = int(x0 + (x1 - x0) * k / 4)
        cv2.putText(img, f"{v:.2f}", (u - 12, y1 + 16), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, f"n={values.size}", (x1 - 60, y1 + 32), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
    return img


def repaint_strip(panels: list[tuple[str, np.ndarray]], focus: np.ndarray, path,
                  window=(160, 160), scale=3) -> None:
    """Figure 8 style: the same window around the repainted line at several moments."""
    ys, xs = np.nonzero(focus)
    if ys.size == 0:
        side_by_side(panels, path, window, scale)
        return
    r0 = int(np.clip(ys.mean() - window[0] // 2, 0, max(0, focus.shape[0] - window[0])))
    c0 = int(np.clip(xs.mean() - window[1] // 2, 0, max(0, focus.shape[1] - window[1])))
    crops = [(t, lab[r0 : r0 + window[0], c0 : c0 + window[1]]) for t, lab in panels]
    tiles = [_title(cv2.resize(_bgr(c), None, fx=scale, fy=scale,
                               interpolation=cv2.INTER_NEAREST), t) for t, c in crops]
    gap = np.full((tiles[0].shape[0], 6, 3), 255, np.uint8)
    out = tiles[0]
    for t in tiles[1:]:
        out = np.hstack([out, gap, t])
    cv2.imwrite(str(path), out)
