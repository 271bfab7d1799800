"""On-vehicle mapping core (paper section III-A): segment -> IPM -> pose graph -> voting grid.

Consumes camera frames (RGB and/or true labels), wheel speed, gyro yaw rate and GNSS fixes with
ns timestamps; produces sealed GridPatch lists (world ENU frame, 0.1 m cells). Semantic points of
a frame wait in the vehicle frame until the pose graph has settled that frame's pose, and are then
put into the world with the optimized pose (paper eq. 5) and voted. Pure: no I/O, no timing."""

import logging
from dataclasses import dataclass

import numpy as np

from common.camera import CameraModel, build_ipm_lookup
from common.classes import NUM_CLASSES, Cls
from common.config import VehicleConfig
from common.geometry import transform_points_2d
from common.messages import GridPatch
from common.segmentation import Segmenter
from services.vehicle.estimator import PoseEstimator
from services.vehicle.patchform import CellsForm
from services.vehicle.voting import VotingGrid, raster_window

logger = logging.getLogger(__name__)

POINT_SCALE = 100.0  # buffered vehicle-frame points are stored as int16 centimetres


@dataclass
class _Buffered:
    t_ns: int
    points_cm: np.ndarray  # int16 (K, 2) vehicle frame
    classes: np.ndarray  # uint8 (K,)


class VehicleMapper:
    """One mapping vehicle's traversal. Verbs: process_odometry/imu/gnss/frame, flush.

    seal_every_frames: committed frames per patch sequence number (each seal emits one patch per
    touched tile with the votes since the previous seal); ipm_stride: pixel subsampling;
    patch_form: what a sealed patch goes up as (services/vehicle/patchform.py)."""

    def __init__(
        self,
        *,
        vehicle: str,
        traversal: str,
        camera: CameraModel,
        segmenter: Segmenter,
        roi_x_min_m: float,
        roi_length_m: float,
        roi_width_m: float,
        estimator: PoseEstimator | None = None,
        seal_every_frames: int = VehicleConfig.seal_every_frames,
        ipm_stride: int = VehicleConfig.ipm_stride,
        min_paint_frames: int = VehicleConfig.min_paint_frames,
        min_symbol_frames: int = VehicleConfig.min_symbol_frames,
        symbol_lane_frames: int = VehicleConfig.symbol_lane_frames,
        patch_form=None,
    ):
        self.vehicle, self.traversal = vehicle, traversal
        self.segmenter = segmenter
        self.ipm = build_ipm_lookup(
            camera, x_min_m=roi_x_min_m, length_m=roi_length_m, width_m=roi_width_m
        )
        self.estimator = estimator or PoseEstimator()
        self.seal_every_frames = seal_every_frames
        self.ipm_stride = ipm_stride
        self.patch_form = patch_form or CellsForm()
        # paint a cell got from fewer frames than this is not sealed: one frame's
        # hallucination never becomes a marking (1: every vote counts)
        self.min_paint_frames = int(min_paint_frames)
        self.min_symbol_frames = int(min_symbol_frames)  # ... of stop lines and ground signs
        self._min_frames = np.full(NUM_CLASSES, self.min_paint_frames, np.int64)
        self._min_frames[[Cls.STOP_LINE, Cls.GROUND_SIGN]] = self.min_symbol_frames
        # a ground sign on a cell that this many frames saw as lane line is not voted (0: off)
        self.symbol_lane_frames = int(symbol_lane_frames)
        self.delta = VotingGrid()  # votes since the last seal
        self.paint_frames = VotingGrid()  # per (cell, paint class): frames that saw it, ditto
        self.grid = VotingGrid()  # the whole local map (sealed votes)
        self.poses: dict[int, np.ndarray] = {}  # committed optimized poses by frame index
        self.seq = 0
        self._buffer: dict[int, _Buffered] = {}
        self._committed = 0
        self._seal_poses: list[np.ndarray] = []  # poses of the frames voted since the last seal

    # -- sensor verbs ------------------------------------------------------------------------

    def process_odometry(self, t_ns, speed_mps) -> None:
        self.estimator.add_odometry(t_ns, speed_mps)

    def process_imu(self, t_ns, yaw_rate_rps) -> None:
        self.estimator.add_imu(t_ns, yaw_rate_rps)

    def process_gnss(self, t_ns: int, xy_m, sigma_m: float, ok: bool) -> None:
        self.estimator.add_gnss(t_ns, xy_m, sigma_m, ok)

    def process_frame(self, t_ns: int, image_rgb=None, labels_true=None) -> list[GridPatch]:
        """A camera frame: segment, IPM, add its pose node, vote every settled frame."""
        labels = self.segment(image_rgb, labels_true)  # 1. class image
        points, classes = self.inverse_perspective(labels)  # 2. ground points, vehicle frame
        self.add_pose(t_ns, points, classes)  # 3. pose node; points wait for it to settle
        return self.commit_settled()  # 4. settled frames -> world -> votes -> sealed patches

    def flush(self) -> list[GridPatch]:
        """End of the drive: settle every remaining frame and seal the rest."""
        patches = self.commit_settled(flush=True)
        return patches + self._seal()

    # -- stages (public so the node can time each) -------------------------------------------

    def segment(self, image_rgb, labels_true) -> np.ndarray:
        return self.segmenter.segment(image_rgb, labels_true)

    def inverse_perspective(self, labels: np.ndarray):
        """Paper eq. 1 through the precomputed lookup: labelled ROI pixels -> vehicle-frame xy."""
        return self.ipm.lookup(labels, stride=self.ipm_stride)

    def add_pose(self, t_ns: int, points_xy_m: np.ndarray, classes: np.ndarray) -> int:
        i = self.estimator.add_frame(t_ns)
        cm = np.round(np.asarray(points_xy_m) * POINT_SCALE).astype(np.int16)
        self._buffer[i] = _Buffered(int(t_ns), cm, np.asarray(classes, np.uint8))
        return i

    def commit_settled(self, flush: bool = False) -> list[GridPatch]:
        """Vote the frames whose poses are settled, with their optimized poses (paper eq. 5)."""
        patches = []
        for i, pose in self.estimator.settled(flush=flush):
            frame = self._buffer.pop(i)
            self.poses[i] = pose
            world_xy = transform_points_2d(pose, frame.points_cm.astype(np.float64) / POINT_SCALE)
            self.delta.add_points(world_xy, frame.classes, frame.t_ns)
            if self._min_frames.max() > 1:
                paint = frame.classes >= Cls.LANE_LINE
                self.paint_frames.add_presence(world_xy[paint], frame.classes[paint])
            self._seal_poses.append(np.asarray(pose, dtype=np.float64))
            self._committed += 1
            if self._committed % self.seal_every_frames == 0:
                patches += self._seal()
        return patches

    def local_map(self, margin_m: float = 2.0):
        """(labels, x0_m, y0_m): argmax raster of everything voted so far (sealed or not)."""
        whole = VotingGrid()
        whole.merge(self.grid)
        whole.merge(self.delta)
        return raster_window(whole, margin_m)

    def trajectory(self) -> dict[str, np.ndarray]:
        """The committed frames in order: t_ns (N,), pose (N, 3) the optimized (x, y, yaw) they
        were voted with, gnss_covered (N,), odom_delta (N, 3) the raw odometry since the
        previous frame (uncalibrated wheel speed and gyro; zeros for the first frame)."""
        est, n = self.estimator, len(self.poses)
        return {
            "t_ns": np.array([est.node_time_ns(i) for i in range(n)], np.int64),
            "pose": np.array([self.poses[i] for i in range(n)], np.float64).reshape(-1, 3),
            "gnss_covered": np.array([est.covered(i) for i in range(n)], bool),
            "odom_delta": est.raw_deltas()[:n].reshape(-1, 3),
        }

    @property
    def frames_committed(self) -> int:
        return self._committed

    @property
    def frames_waiting(self) -> int:
        return len(self._buffer)

    def _seal(self) -> list:
        if self._min_frames.max() > 1:  # paint seen in too few frames: no votes
            self.delta.drop_unconfirmed(self.paint_frames, self._min_frames,
                                        first_class=Cls.LANE_LINE)
            if self.symbol_lane_frames > 0:
                self.delta.drop_class_where(Cls.GROUND_SIGN, self.paint_frames,
                                            other=Cls.LANE_LINE,
                                            min_count=self.symbol_lane_frames)
            self.paint_frames.clear()
        patches = self.delta.patches(self.vehicle, self.traversal, self.seq)
        patches = self.patch_form.finish(patches, np.array(self._seal_poses).reshape(-1, 3))
        self.grid.merge(self.delta)
        self.delta.clear()
        self._seal_poses = []
        if patches:
            self.seq += 1
        return patches
