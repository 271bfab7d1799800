"""Drive logs: the on-disk format the simulator writes and the vehicle and localizer read.

A drive log is a directory:

    log.json        format version, vehicle id, traversal id, profile (mapping | production),
                    world {name, origin_lat, origin_lon}, camera (CameraModel.to_dict),
                    and free-form notes (e.g. the source dataset)
    streams.npz     numpy arrays, all times int64 nanoseconds on one clock:
                      frame_t_ns [F]             camera frame times
                      frame_pose_true [F, 3]     true (x, y, yaw) of the vehicle; NaN if unknown
                      odom_t_ns [O], odom_speed_mps [O]         wheel odometry (forward speed)
                      imu_t_ns [I], imu_yaw_rate_rps [I]        gyro z (yaw rate)
                      gnss_t_ns [G], gnss_xy_m [G, 2], gnss_sigma_m [G], gnss_ok [G] (bool)
                      truth_t_ns [T], truth_pose [T, 3]         dense ground truth (optional)
    frames/NNNNNN.jpg   RGB camera frame i (JPEG; absent for label-only logs)
    labels/NNNNNN.png   true class image of frame i (uint8 PNG; optional)

Positions are in the world's local ENU frame (metres); yaw in radians from +x (east).
A real dataset converts into this format (see services/sim/comma2k19.py)."""

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from common.camera import CameraModel
from common.errors import DriveLogError

FORMAT_VERSION = 1
STREAM_KEYS = (
    "frame_t_ns", "frame_pose_true", "odom_t_ns", "odom_speed_mps", "imu_t_ns",
    "imu_yaw_rate_rps", "gnss_t_ns", "gnss_xy_m", "gnss_sigma_m", "gnss_ok",
)
OPTIONAL_KEYS = ("truth_t_ns", "truth_pose")


@dataclass
class DriveLogMeta:
    vehicle: str
    traversal: str
    profile: str  # "mapping" | "production"
    world: dict  # {name, origin_lat, origin_lon}
    camera: CameraModel
    notes: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "format": FORMAT_VERSION, "vehicle": self.vehicle, "traversal": self.traversal,
            "profile": self.profile, "world": self.world, "camera": self.camera.to_dict(),
            "notes": self.notes,
        }


class DriveLog:
    """Read access to a drive log directory; streams load eagerly, frames lazily."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        try:
            raw = json.loads((self.root / "log.json").read_text())
            npz = np.load(self.root / "streams.npz")
            self.streams = {k: npz[k] for k in npz.files}
        except (OSError, ValueError, KeyError) as exc:
            raise DriveLogError(f"{self.root}: not a drive log ({exc})") from exc
        if raw.get("format") != FORMAT_VERSION:
            raise DriveLogError(
                f"{self.root}: format {raw.get('format')!r}, expected {FORMAT_VERSION}"
            )
        missing = [k for k in STREAM_KEYS if k not in self.streams]
        if missing:
            raise DriveLogError(f"{self.root}: streams.npz lacks {missing}")
        self.meta = DriveLogMeta(
            vehicle=raw["vehicle"], traversal=raw["traversal"], profile=raw["profile"],
            world=raw["world"], camera=CameraModel.from_dict(raw["camera"]),
            notes=raw.get("notes", {}),
        )

    def __len__(self) -> int:
        return len(self.streams["frame_t_ns"])

    def image(self, i: int) -> np.ndarray | None:
        """RGB uint8 (H, W, 3) of frame i, or None for a label-only log."""
        path = self.root / "frames" / f"{i:06d}.jpg"
        if not path.exists():
            return None
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise DriveLogError(f"{path}: unreadable image")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def labels(self, i: int) -> np.ndarray | None:
        path = self.root / "labels" / f"{i:06d}.png"
        if not path.exists():
            return None
        lab = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if lab is None:
            raise DriveLogError(f"{path}: unreadable label image")
        return lab


class DriveLogWriter:
    """Writes a drive log: frames as they come, streams and meta on close()."""

    def __init__(self, root: str | os.PathLike, meta: DriveLogMeta, jpeg_quality: int = 92):
        self.root = Path(root)
        self.meta = meta
        self.jpeg_quality = jpeg_quality
        (self.root / "frames").mkdir(parents=True, exist_ok=True)
        (self.root / "labels").mkdir(parents=True, exist_ok=True)

    def write_frame(self, i: int, image_rgb: np.ndarray | None, labels: np.ndarray | None) -> None:
        if image_rgb is not None:
            cv2.imwrite(str(self.root / "frames" / f"{i:06d}.jpg"),
                        cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR),
                        [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if labels is not None:
            cv2.imwrite(str(self.root / "labels" / f"{i:06d}.png"), labels.astype(np.uint8))

    def close(self, streams: dict[str, np.ndarray]) -> None:
        missing = [k for k in STREAM_KEYS if k not in streams]
        if missing:
            raise DriveLogError(f"drive log streams lack {missing}")
        np.savez(self.root / "streams.npz", **{k: np.asarray(v) for k, v in streams.items()})
        tmp = self.root / "log.json.tmp"
        tmp.write_text(json.dumps(self.meta.to_json(), indent=1))
        os.replace(tmp, self.root / "log.json")  # log.json last: its presence marks a complete log
