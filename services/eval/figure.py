"""eval.png: each drive's mean x, y and yaw error (dots) next to the paper's mean (line), and the
CDF of the frame position errors over every drive's frames with markings in view."""

import cv2
import numpy as np

from services.eval.summary import PAPER_MEAN

W, H, PAD = 360, 300, 40
FONT = cv2.FONT_HERSHEY_SIMPLEX
INK, GRID, PAPER, DOT = (30, 30, 30), (215, 215, 215), (40, 40, 200), (180, 110, 30)


def _axes(title: str, y_max: float, unit: str) -> np.ndarray:
    img = np.full((H, W, 3), 255, np.uint8)
    cv2.rectangle(img, (PAD, PAD // 2), (W - 10, H - PAD), INK, 1)
    for f in (0.25, 0.5, 0.75):
        y = int(H - PAD - f * (H - 1.5 * PAD))
        cv2.line(img, (PAD + 1, y), (W - 11, y), GRID, 1)
        cv2.putText(img, f"{f * y_max:.3g}", (2, y + 4), FONT, 0.33, INK, 1, cv2.LINE_AA)
    cv2.putText(img, f"{title} [{unit}]", (PAD, 14), FONT, 0.45, INK, 1, cv2.LINE_AA)
    return img


def _y(value: float, y_max: float) -> int:
    return int(H - PAD - min(value / y_max, 1.0) * (H - 1.5 * PAD))


def per_drive_panel(name: str, means: list[float], unit: str) -> np.ndarray:
    """One dot per drive (sorted), the paper's mean as a red line."""
    values = sorted(m for m in means if m is not None)
    y_max = max([PAPER_MEAN.get(name, 0.0) * 2.0, *values, 1e-6]) * 1.1
    img = _axes(f"per-drive mean {name}", y_max, unit)
    if name in PAPER_MEAN:
        y = _y(PAPER_MEAN[name], y_max)
        cv2.line(img, (PAD + 1, y), (W - 11, y), PAPER, 2)
        cv2.putText(img, "paper", (W - 60, y - 4), FONT, 0.4, PAPER, 1, cv2.LINE_AA)
    for i, v in enumerate(values):
        x = int(PAD + (i + 0.5) * (W - 10 - PAD) / max(len(values), 1))
        cv2.circle(img, (x, _y(v, y_max)), 4, DOT, -1, cv2.LINE_AA)
    cv2.putText(img, f"{len(values)} drives", (PAD + 4, H - PAD + 16), FONT, 0.4, INK, 1,
                cv2.LINE_AA)
    return img


def cdf_panel(errors_m: list[float]) -> np.ndarray:
    """CDF of frame position errors (m), x up to the 99th percentile."""
    e = np.sort(np.asarray(errors_m, float))
    x_max = float(np.percentile(e, 99)) * 1.05 if len(e) else 1.0
    img = _axes("CDF of frame position error", 1.0, "share")
    if len(e):
        xs = PAD + np.clip(e / x_max, 0, 1) * (W - 10 - PAD)
        ys = H - PAD - (np.arange(1, len(e) + 1) / len(e)) * (H - 1.5 * PAD)
        cv2.polylines(img, [np.stack([xs, ys], 1).astype(np.int32)], False, DOT, 2, cv2.LINE_AA)
    cv2.putText(img, f"0 .. {x_max:.3f} m, {len(e)} frames", (PAD + 4, H - PAD + 16), FONT,
                0.4, INK, 1, cv2.LINE_AA)
    return img


def eval_figure(scores: list[dict], path) -> None:
    panels = [per_drive_panel(k, [s["markings_in_view"][k]["mean"] for s in scores], unit)
              for k, unit in (("x_m", "m"), ("y_m", "m"), ("yaw_deg", "deg"))]
    panels.append(cdf_panel([e for s in scores for e in s.get("errors_m", [])]))
    top, bottom = np.hstack(panels[:2]), np.hstack(panels[2:])
    cv2.imwrite(str(path), np.vstack([top, bottom]))
