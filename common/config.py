"""Typed, sectioned configuration: frozen dataclasses with defaults in code.

Precedence: defaults < TOML file (`--config`) < env `ROADMAP_<SECTION>__<FIELD>` < `--set
section.field=value`. Values in env and --set are parsed as TOML values (`3`, `0.5`, `true`,
`[1, 2]`, `"text"`), and bare words fall back to strings. Unknown sections or fields and wrong
types raise ConfigError naming the offending key."""

import dataclasses
import os
import tomllib
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field

from common.errors import ConfigError

ENV_PREFIX = "ROADMAP_"


# what the segmenter does with the mirror image of a frame (SegmentationConfig.flip,
# common.segmentation.OnnxSegmenter's `flip`, train-seg --set-flip): one pass on the image,
# two passes averaged, or one pass a frame on the image and on its mirror in turn
FLIP_MODES = ("off", "average", "alternate")
# segmentation.kind: the packaged ONNX model, or the simulator's corrupted true labels
SEGMENTER_KINDS = ("onnx", "truth")
PATCH_FORMS = ("cells", "sparse")  # vehicle.patch_form (services/vehicle/patchform.py)


@dataclass(frozen=True)
class BusConfig:
    """How a process reaches Zenoh (a router's client by default; multicast scouting always off)."""

    mode: str = "client"
    connect: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    listen: list[str] = field(default_factory=list)
    lease_ms: int = 3000  # failure detection of hung processes (ZENOH.md 1.6)
    shared_memory: bool = False  # off: avoids zenoh#2628 (SHM query/reply drops under load)
    query_timeout_s: float = 5.0
    # mutual TLS (common/security.py, deploy/README.md): a folder with ca.pem and <role>.pem +
    # <role>.key for the roles that run here (`roadmap certs`); endpoints must then be tls/...
    # and a router enforces the role ACL. Empty: plain tcp, no access control
    tls_dir: str = ""  # folder of ca.pem + <role>.pem/.key: mutual TLS and the role ACL
    # largest message a link reassembles (transport/link/rx/max_message_size; zenoh's default
    # is 1 GiB): what one sender can make a router or client buffer per message
    max_message_bytes: int = 64 << 20  # largest message a link reassembles (0: zenoh's 1 GiB)


@dataclass(frozen=True)
class CameraConfig:
    """Front camera: pinhole + OpenCV distortion; mounting in the vehicle frame (x fwd, y left,
    z up)."""

    width: int = 640
    height: int = 360
    fx: float = 460.0
    fy: float = 460.0
    cx: float = 320.0
    cy: float = 180.0
    dist: list[float] = field(default_factory=lambda: [-0.05, 0.01, 0.0, 0.0, 0.0])
    x_m: float = 1.8  # forward of the rear axle
    y_m: float = 0.0
    height_m: float = 1.5
    pitch_deg: float = 4.0  # looking down
    roll_deg: float = 0.0
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class GridConfig:
    shards: int = 2
    shard_map: dict[str, int] = field(default_factory=dict)  # "rx,ry" -> shard, overrides hashing
    # how vehicles address the cloud (common/keys.py): "shard" = roadmap/ingest/s<owner> (the
    # SQLite shards, needs grid.shards); "region" = roadmap/region/<rx>/<ry>/ingest (the
    # PostgreSQL workers that hold regions by lease, services/merger/worker.py; no shard count)
    routing: str = "shard"


@dataclass(frozen=True)
class RoiConfig:
    """IPM region of interest in the vehicle frame (paper: 12 m ahead x 8 m wide)."""

    x_min_m: float = 3.0
    length_m: float = 12.0
    width_m: float = 8.0


@dataclass(frozen=True)
class DemoConfig:
    """`roadmap demo` / `roadmap up`: drive lengths, segmenter, time limits of the local fleet."""

    images: bool = False  # render camera frames for every drive even with segmentation.kind truth
    max_km: float = 0.4  # length of each simulated drive
    small_max_km: float = 0.2  # --small (the localizer needs ~100 m to converge)
    drives: int = 1  # mapping drives per vehicle
    # a fleet whose shared route's first max_km touch fewer regions than there are shards gets
    # this many more mapping vehicles on the world's route reaching most other regions (2: its
    # cells get merger.min_votes), so every shard has work (services/demo/spread.py; not --small)
    spread_vehicles: int = 2
    # the SQLite demo sets grid.shard_map (when empty) to spread the regions its mapping drives
    # touch over the shards, heaviest first to the least loaded (not --small)
    spread_shards: bool = True
    render_workers: int = 2  # drives rendered at once, one process each (frames for the model)
    repaint_drives_before: int = 2  # per vehicle, old paint
    repaint_drives_after: int = 5  # single traversals after the repaint, one at a time
    repaint_min_km: float = 0.3  # repaint drives reach the moved line (120-250 m into the route)
    chaos_after_s: float = 0.0  # --chaos kills this long after the shard applied its first patch
    vehicle_timeout_s: float = 600.0
    localizer_timeout_s: float = 600.0
    # localize the production drive a second time on the uncompressed map (the codec's share
    # of the error, report.json localization.uncompressed_map; off: about a minute of demo)
    compare_raw_map: bool = False
    query_timeout_s: float = 5.0


@dataclass(frozen=True)
class SegmentationConfig:
    """Which segmenter the mapping vehicles and the production car run on camera frames
    (common.segmentation.segmenter_for), and how the ONNX one runs."""

    # "onnx": the packaged model (or model_path) on rendered frames, the paper's pipeline (the
    # demo renders every drive's images; a log without images falls back to "truth");
    # "truth": the simulator's corrupted true labels, for tests and ablations
    kind: str = "onnx"
    model_path: str = ""  # empty: common/models/roadseg.onnx shipped with the package
    intra_op_threads: int = 1
    # rows above the rays rising this far above level (degrees) show no road: labelled none,
    # not segmented (10: the default camera's top 48 of 360 rows)
    sky_margin_deg: float | None = None  # < 0: every row; empty: the model's own, else 10
    # paint borders by the model's learned classifier (metadata `border_net`) if it has one
    border_net: bool = True  # false: its brightness rule, 1-2 ms a frame faster, lower IoU
    # the mirror image: "average" runs the network on image and mirror (twice the time),
    # "alternate" on one of them a frame in turn, "off" on the image (costs: MODEL_CARD.md)
    # "alternate" (one pass a frame) is the default: two passes ("average", the packaged file's
    # own) cost 1.5-1.7x the time, over the 15 ms a frame on one core (MODEL_CARD.md)
    flip: str = "alternate"  # empty: the model's own; else off, average or alternate (FLIP_MODES)
    # segment only the rows the role's IPM ROI reads, the network seeing 80 rows of context
    # above them; the rows above the ROI (less 5) are labelled none (the mapper's 3-11 m: 232
    # rows of 360 through the network)
    roi_rows_only: bool = True


@dataclass(frozen=True)
class LocalizerConfig:
    """User-end localizer: map access, point thinning, ICP, EKF, initialization."""

    map_codec: str = "contour"  # "contour" (compressed tiles) | "raw" (uncompressed, comparison)
    truth_seed: int = 1  # GroundTruthSegmenter corruption seed (another than the fleet's)
    # "onnx": as vehicle.paint_min_margin, for ICP's points
    paint_min_margin: float = 0.0  # logits a marking pixel's class must lead by (0: off)
    ipm_stride: int = 2  # take every n-th pixel row and column of the label image
    max_points: int = 700  # points per frame into ICP
    road_fraction: float = 0.25  # share of road-surface points among them
    icp_iterations: int = 12
    icp_gate_start_m: float = 1.5
    icp_gate_end_m: float = 0.4
    icp_huber_m: float = 0.1
    icp_refine_iterations: int = 6  # sub-cell refinement on the lines' likelihood field (0: off)
    # the lane-line field is a plateau, not a ridge: its mask is widened first (TileCache)
    field_line_grow_cells: int = 5  # square kernel, cells (1: not widened)
    # a lane-lines-only match holds the along-road position at the prediction (Localizer._held)
    hold_along_road_m: float = 0.02  # sigma of the hold, m (0: off)
    hold_below_m: float = 0.1  # ... once the filter's along-road sigma is below this, m
    # ... and the odometry scale learns nothing from a held match (its estimate and variance
    # stand; services/localizer/ekf.py consider form): summed frame after frame, the hold's
    # pseudo-measurement shrank the scale's sigma to 0.07 % while it was 1.2 % wrong (off:
    # mixed on held-out drives, docs/RESULTS.md, "491-493"; mixed again with the matches'
    # shared error, "Fault limits on the gyro bias and the scale")
    hold_considers_scale: bool = False
    # far points' residuals along the viewing ray weigh less: a pixel is r^2 / (f h) m there
    ipm_sigma_px: float = 1.0  # label noise of the IPM points, pixels (0: off; IpmNoise)
    icp_cov_scale: float = 60.0  # single-frame ICP is over-confident (correlated points, vibration)
    gnss_inflate: float = 1.5  # consumer GNSS has a slowly varying bias: trust it less
    # the GNSS as integrity monitor: a mean residual (fix minus pose) over the last
    # gnss_check_fixes fixes beyond gnss_alert_sigmas x their reported sigma restarts the
    # filter (a lock onto a parallel road 10 m over; services/localizer/gnss_check.py; 0: off)
    gnss_check_fixes: int = 25
    gnss_alert_sigmas: float = 3.0
    speed_sigma_rel: float = 0.005  # the odometry scale itself is estimated
    # a wheel's scale error is all but constant: a faster walk lets ICP's dash-periodic
    # along-road errors swing the scale, and the position saw-tooth with the dashes
    scale_walk_per_s: float = 3e-5  # random walk of that scale, 1/sqrt(s)
    # that scale's prior sigma at each (re)start of the filter: wheel-speed odometry is good
    # to 1-2 % (tyre wear, pressure, load); at 3 %, the first along-road fixes after a start
    # off along the road were read as scale, which ran to its 5 % clamp
    scale_sigma0: float = 0.015
    # ... and, frozen at the start, it learns nothing from the matches after a (re)start until
    # the first ok pose or a match that pins the along-road position to within
    # scale_thaw_fix_sigma_m: a start metres off along the road is pulled back by its first
    # fixes, which a learning filter reads as scale (docs/RESULTS.md, "The scale frozen at the
    # start"); 0.05 m kept it frozen through a whole drive with few stop lines and broke
    # integrity there
    scale_frozen_at_start: bool = True
    scale_thaw_fix_sigma_m: float = 0.1
    # ... and, frozen, its covariance with the pose is kept right through every update (the
    # Schmidt-Kalman "consider" form), so the match that thaws it learns from all the travel
    # since the start, not the last frame's (False: dropped at each update)
    scale_frozen_considered: bool = True
    # what successive matches share of their error (the map's error of the marking they all
    # see, the camera's pitch): a state, a Gauss-Markov process over the distance driven with
    # this stationary sigma and correlation length, so that one marking seen over many frames
    # counts as one fix (services/localizer/ekf.py MatchBias; 0 and 0: off, matches independent;
    # 0.05 m cost a suite drive its heading; a yaw part broke Karlsruhe s492 further:
    # docs/RESULTS.md, "The matches' shared error")
    match_bias_sigma_m: float = 0.03
    match_bias_yaw_deg: float = 0.0
    match_bias_length_m: float = 20.0
    yaw_rate_sigma_dps: float = 0.3
    max_position_sigma_m: float = 1.0  # the filter trusts itself below this (re-init above)
    # integrity: a pose is reported ok only while its protection level (integrity_k x the
    # position sigma) lies within the alert limit: a lane-level error must never read as ok
    alert_limit_m: float = 0.5
    integrity_k: float = 3.0
    # ... and the position sigma widened by the matches' net correction over the last this many
    # frames: a filter still being pulled one way has not converged, whatever its covariance says
    settle_frames: int = 10
    # ... and, after a (re)start or a gap of settle_frames without a match, since then, for up
    # to this many frames
    reacquire_settle_frames: int = 50
    # road surface alone does not tell a road from its neighbour or its own length: frames with
    # fewer marking points than this are not matched (the filter dead-reckons on odometry and
    # GNSS, its sigma grows), nor is a submap with fewer than init_min_marking_points initialized
    min_marking_points: int = 30
    init_min_marking_points: int = 150
    # the along-road hold does not observe the along-road position: its sigma for the integrity
    # flag grows by this share of the distance driven since the last along-road fix
    hold_drift_per_m: float = 0.003
    # ... and without any match (no markings in view), by this share: the odometry's heading
    # and scale errors the filter does not model (a 0.3 deg yaw error is 0.5 % across)
    dead_reckoning_drift_per_m: float = 0.005
    # ... and by the odometry scale's sigma times the distance driven since the last match
    # that pinned the along-road position to within this sigma: lane-line matches with weak
    # along-road information, summed frame after frame as if independent, shrink the filter's
    # sigma while an unlearnt scale error walks the position along the road (0: off; the
    # frozen scale above needs it)
    along_fix_sigma_m: float = 0.2
    # ... and not trusted for settle_frames after a match shifted the pose beyond this squared
    # Mahalanobis distance of what its covariance expected (chi-square, 2 dof; 20: p 5e-5; 0: off)
    integrity_consistency_chi2: float = 20.0
    # ... and such a match teaches the odometry scale nothing (its pose still moves): dash ends
    # that pull a pose 0.5 m off a few centimetres a frame swung a start's scale 3 % wrong
    scale_skips_inconsistent: bool = True
    # ... and not trusted while an accepted match leaves fewer than this share of its frame's
    # marking points within integrity_paint_fit_tol_m of the map's markings of their class:
    # road points fit anywhere along a road, and a match they made can be metres off with a
    # covariance of centimetres (0: off). A pose half a metre off leaves its paint that far
    # from the map's; 0.3 m keeps far points' noise in. Trusted again once the latest match
    # fits and at most integrity_paint_misses of the last settle_frames did not; a marking of
    # any class will do with integrity_paint_any_class (both relaxations: more ok frames, and
    # more wrong ones on held-out drives; services/localizer/paint_check.py)
    integrity_min_paint_fit: float = 0.3
    integrity_paint_fit_tol_m: float = 0.3
    integrity_paint_misses: int = 0
    integrity_paint_any_class: bool = False
    # when fewer than paint_lost_fit of the last paint_lost_matches accepted matches left their
    # paint on the map's, the submap is searched around the pose, and the filter restarts where
    # its paint fits the map's by paint_relocate_margin (a share of its points) better (0: never)
    paint_lost_matches: int = 30
    paint_lost_fit: float = 0.3
    paint_relocate_margin: float = 0.2
    # ... and, searched the same way (each class's share weighed alike), after a match whose
    # frame has paint_misplaced_min_points or more points of a stop line, crosswalk or ground
    # sign, the map one within paint_misplaced_reach_m of most of them, and fewer than
    # integrity_min_paint_fit of them on it (a miss for the flag too; 0: off); lane lines fit
    # anywhere along the road
    paint_misplaced_min_points: int = 100
    paint_misplaced_reach_m: float = 3.0
    # a match that leaves less than this share of its frame's paint on the map's markings of
    # their class is not fused (it counts as a miss for the flag and the lost test): road
    # points and paint the map lacks pull the pose and the heading anywhere (0: off; 0.1
    # helped one held-out drive and cost others their heading: docs/RESULTS.md, "491-493")
    paint_fuse_min_fit: float = 0.0
    init_radius_m: float = 6.0  # coarse search half-size around the GNSS fix
    init_travel_m: float = 12.0  # metres of frames gathered before the coarse search
    init_frames: int = 30
    # a start among rivals as good as the best match (overlap within the margin: the next dash
    # of a periodic line, a mirror-image pose) begins at the one the GNSS fixes clearly favour
    # (Localizer._gnss_consistent), else at the most overlap; the others stay rivals either way
    init_gnss_tiebreak: bool = True
    reinit_bad_frames: int = 30
    fetch_radius_m: float = 40.0  # tiles within this distance of the car are fetched
    prefetch_ahead_m: float = 60.0  # and these along the direction of travel
    cache_tiles: int = 25
    publish: bool = True  # publish roadmap/pose/<vehicle>
    recent_frames: int = 0  # also match a sample of the last n frames' points (odometry-chained)
    # init: icp_gate_start_m; grows with the filter's sigma; 1.5 m let a frame jump a dash
    icp_track_gate_m: float = 0.5  # first correspondence gate while tracking, m
    # ICP estimates the camera's pitch per frame (0.3 deg moves a point 12 m ahead by 0.5 m)
    attitude_roll: bool = False  # roll too (else pitch only; roll hardly moves ground points)
    attitude_sigma_deg: float = 0.3  # prior of the per-frame attitude offset


@dataclass(frozen=True)
class VehicleConfig:
    """On-vehicle mapper (services/vehicle): pose settling, calibration, sealing, upload."""

    settle_lag_s: float = 1.0  # a frame's points wait for a good GNSS fix this much later
    max_wait_s: float = 120.0  # ... but never longer than this (very long outages)
    calib_window_s: float = 5.0  # odometry scale / gyro bias calibration window
    seal_every_frames: int = 100  # committed frames per patch sequence number
    ipm_stride: int = 1  # pixel subsampling of the IPM lookup
    # a 0.3 deg pitch vibration moves a ground point by range^2 / height x 0.005 (0.8 m at 15 m)
    max_range_m: float = 11.0  # vote only ground points up to this far ahead (caps roi.length_m)
    # what a sealed patch goes up as: "cells" (packed per-cell votes, ~1 byte per cell seen) or
    # "sparse" (common/sparse.py: polygons + key poses + paint shares, ~1 % of those bytes)
    patch_form: str = "sparse"
    # seal_every_frames of the sparse form, whose bytes are mostly per patch (seams, key poses)
    sparse_seal_every_frames: int = 300
    upload_batch: int = 16  # patches per IngestBatch
    upload_timeout_s: float = 5.0  # per ingest query
    backoff_min_s: float = 0.05
    backoff_max_s: float = 2.0
    truth_seed: int = 0  # GroundTruthSegmenter corruption seed (deterministic re-mapping)
    # "onnx": unsure paint votes nothing: fewer false paint votes, a few true ones lost
    paint_min_margin: float = 1.0  # logits a marking pixel's class must lead the next by (0: off)
    # ... for stop lines and ground signs, which the model paints on plain asphalt and across
    # junction lines: held-out ROI pixels far from any true one at 1 / 3 logits, stop line 3723
    # / 1144, ground sign 190 / 0, with 93 / 73 and 90 / 68 % of the true ones kept
    symbol_min_margin: float = 3.0
    # a cell's paint of a class seen in fewer frames than this is not voted (sealed out): one
    # frame's hallucination never becomes a marking (1: off)
    min_paint_frames: int = 2
    # ... for stop lines and ground signs: 2 with merger.min_stop_cells below (the suite's stop
    # recall min / median 0.57 / 0.84 -> 0.67 / 0.88 at a like precision; docs/RESULTS.md)
    min_symbol_frames: int = 2
    # a ground sign on a cell that this many frames saw as lane line is not voted (0: off):
    # the model calls pieces of thick lane lines sign (seed 0 / 1 Karlsruhe demo drives
    # replayed: false sign cells 55 / 65 -> 29 / 33, other classes unchanged)
    symbol_lane_frames: int = 1


@dataclass(frozen=True)
class MergerConfig:
    """Tile merger shard (services/merger): evidence rule, debounce, durability."""

    window_traversals: int = 3  # ballots of the newest observing traversals per cell (repaint in 2)
    footprint_cells: int = 9  # a traversal's unvoted cells inside its closed footprint vote none
    min_votes: int = 2  # votes behind a label, else unknown
    # a ground-sign blob (gaps up to 0.3 m joined) of fewer cells is decided again without its
    # sign ballots: a painted sign (an arrow, a bicycle) covers 1-1.5 m^2 (100-150 cells)
    min_sign_cells: int = 30
    # ... and a stop-line blob of fewer cells without its stop-line ballots (0 or 1: off). A stop
    # line spans a lane, 0.3-0.5 m x 3 m (90-150 cells); the model's stray stop paint comes in
    # pieces of a few
    min_stop_cells: int = 20
    # a traversal out of every cell's window is dropped from memory once it is this much older
    # than the tile's window-th newest traversal (services/merger/shard.py; < 0: never)
    retire_after_s: float = 3600.0
    debounce_s: float = 0.5  # recompress / publish changed tiles at most this often
    debounce_max_s: float = 2.0  # ... and, while batches keep coming, at the latest this late
    max_batch_patches: int = 4096
    max_batch_cells: int = 4_000_000
    sqlite_synchronous: str = "FULL"  # FULL: the ack survives power loss, not just kill -9
    ingest_queue: int = 256
    ingest_group: int = 32  # waiting ingest queries stored in one transaction (group commit)
    # hostile input (services/merger/throttle.py, deploy/README.md): an ingest payload larger
    # than this is refused before it is decoded (a vehicle's 16-patch batch is well under 1 MB)
    max_ingest_bytes: int = 8 << 20  # larger ingest payloads are refused before decoding
    # token bucket per client (the vehicle id the query carries as attachment): a query costs
    # one token per started ingest_token_bytes of payload; over its rate a vehicle is answered
    # "throttled" at once (it backs off and retries) and the others' queries keep flowing. A
    # vehicle seals a patch per tile about every 10 s of driving; the burst covers the backlog of
    # a long outage (200 batches of 16 patches). <= 0: no throttle (services/merger/flood.py
    # measures it: one flooding vehicle against three normal ones)
    ingest_rate_per_s: float = 20.0  # tokens per second per vehicle (<= 0: no throttle)
    ingest_burst: float = 200.0  # a vehicle's bucket size
    ingest_token_bytes: int = 256 << 10  # a query costs a token per started this many bytes
    ingest_clients: int = 4096  # buckets kept (least recently seen clients forgotten)
    # a throttled query's ack is sent this late (at most ingest_queue of them held at once):
    # a sender that retries without backing off still sends no faster than one per delay
    throttle_delay_s: float = 1.0  # a throttled query is answered this late
    # a shard is one core's work: N shards with N threads each oversubscribe N cores
    opencv_threads: int = 1  # OpenCV threads per shard process (0: OpenCV's, one per core)
    # durable store: "" = one SQLite file per shard (the embedded default); "postgresql://..."
    # = one shared PostgreSQL database (services/merger/pgstore.py), run by `roadmap worker`
    store: str = ""
    lease_s: float = 4.0  # a worker's region lease lasts this long unless renewed (fencing epoch)
    lease_renew_s: float = 0.5  # the worker's control tick: renew, claim, release regions
    # "rx,ry" -> worker id: that worker holds the region while it is alive (else rendezvous
    # hashing over the live workers decides, as for every region not listed)
    region_owners: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class WorldConfig:
    """Where the world's local ENU frame lies on the globe (DESIGN.md: Frames): the geodetic
    origin that map exports (GeoJSON, Lanelet2 OSM) and the viewer convert metres about. Empty:
    taken from the drive logs of a demo's output folder (their world's origin)."""

    origin_lat_deg: float | None = None  # WGS84 latitude of x = y = 0
    origin_lon_deg: float | None = None  # WGS84 longitude of x = y = 0


@dataclass(frozen=True)
class RoadmapConfig:
    bus: BusConfig = field(default_factory=BusConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    roi: RoiConfig = field(default_factory=RoiConfig)
    demo: DemoConfig = field(default_factory=DemoConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    localizer: LocalizerConfig = field(default_factory=LocalizerConfig)
    merger: MergerConfig = field(default_factory=MergerConfig)
    world: WorldConfig = field(default_factory=WorldConfig)


# -- loading -----------------------------------------------------------------------------------


def _parse_scalar(text: str):
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _coerce(value, tp, where: str):
    origin = typing.get_origin(tp)
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp in (int, float, str, bool):
        if not isinstance(value, tp) or (tp is int and isinstance(value, bool)):
            raise ConfigError(f"{where}: expected {tp.__name__}, got {value!r}")
        return value
    if origin is list:
        (item,) = typing.get_args(tp)
        if isinstance(value, str) and item is str:
            value = [v for v in value.split(",") if v]
        if not isinstance(value, list):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        return [_coerce(v, item, where) for v in value]
    if origin is dict:
        _, vt = typing.get_args(tp)
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a table, got {value!r}")
        return {str(k): _coerce(v, vt, where) for k, v in value.items()}
    if origin in (types.UnionType, typing.Union):
        if value is None or value == "":
            return None
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return _coerce(value, args[0], where)
    raise ConfigError(f"{where}: unsupported config type {tp}")


def _merge(obj, overrides: Mapping, where: str):
    if not dataclasses.is_dataclass(obj):
        raise ConfigError(f"{where}: not a section")
    hints = typing.get_type_hints(type(obj))
    changes = {}
    for key, value in overrides.items():
        if key not in hints:
            known = ", ".join(sorted(hints))
            msg = f"unknown config key {where}.{key} (known: {known})"
            raise ConfigError(msg.replace("..", "."))
        current = getattr(obj, key)
        sub = f"{where}.{key}" if where else key
        if dataclasses.is_dataclass(current):
            if not isinstance(value, Mapping):
                raise ConfigError(f"{sub}: expected a table")
            changes[key] = _merge(current, value, sub)
        else:
            changes[key] = _coerce(value, hints[key], sub)
    return dataclasses.replace(obj, **changes)


def _nest(dotted: Mapping[str, object]) -> dict:
    out: dict = {}
    for key, value in dotted.items():
        parts = key.split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return out


def _env_overrides(env: Mapping[str, str]) -> dict:
    dotted = {}
    for key, value in env.items():
        if key.startswith(ENV_PREFIX) and "__" in key:
            path = key[len(ENV_PREFIX) :].lower().replace("__", ".")
            dotted[path] = _parse_scalar(value)
    return _nest(dotted)


def _set_overrides(items: list[str]) -> dict:
    dotted = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set expects section.key=value, got {item!r}")
        key, value = item.split("=", 1)
        dotted[key.strip()] = _parse_scalar(value.strip())
    return _nest(dotted)


def load_config(
    path: str | os.PathLike | None = None,
    *,
    env: Mapping[str, str] | None = None,
    sets: list[str] | None = None,
    base: RoadmapConfig | None = None,
) -> RoadmapConfig:
    """Defaults < file < env < --set; validated once here."""
    cfg = base or RoadmapConfig()
    if path:
        try:
            with open(path, "rb") as f:
                cfg = _merge(cfg, tomllib.load(f), "")
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"cannot read config {path}: {exc}") from exc
    cfg = _merge(cfg, _env_overrides(os.environ if env is None else env), "")
    cfg = _merge(cfg, _set_overrides(sets or []), "")
    _validate(cfg)
    return cfg


def with_sections(cfg: RoadmapConfig, sections: Mapping) -> RoadmapConfig:
    """cfg with the values of a parsed TOML table ({section: {key: value}}) over it, coerced and
    validated as a config file's are (a stored run's config.toml writes None as "")."""
    cfg = _merge(cfg, sections, "")
    _validate(cfg)
    return cfg


def _validate(cfg: RoadmapConfig) -> None:
    if cfg.grid.shards < 1:
        raise ConfigError("grid.shards must be >= 1")
    if cfg.bus.mode not in ("client", "peer", "router"):
        raise ConfigError(f"bus.mode must be client, peer or router, got {cfg.bus.mode!r}")
    if cfg.camera.width <= 0 or cfg.camera.height <= 0:
        raise ConfigError("camera.width and camera.height must be positive")
    if len(cfg.camera.dist) not in (4, 5, 8):
        raise ConfigError("camera.dist needs 4, 5 or 8 OpenCV coefficients")
    if cfg.segmentation.kind not in SEGMENTER_KINDS:
        raise ConfigError(f"segmentation.kind must be one of {', '.join(SEGMENTER_KINDS)}, "
                          f"got {cfg.segmentation.kind!r}")
    if cfg.segmentation.flip not in ("", *FLIP_MODES):
        raise ConfigError(f"segmentation.flip must be empty (the model's own) or one of "
                          f"{', '.join(FLIP_MODES)}, got {cfg.segmentation.flip!r}")
    if cfg.vehicle.patch_form not in PATCH_FORMS:
        raise ConfigError(f"vehicle.patch_form must be one of {', '.join(PATCH_FORMS)}, "
                          f"got {cfg.vehicle.patch_form!r}")
    if cfg.grid.routing not in ("shard", "region"):
        raise ConfigError(f"grid.routing must be shard or region, got {cfg.grid.routing!r}")
    if cfg.merger.store and not cfg.merger.store.startswith(("postgresql://", "postgres://")):
        raise ConfigError(f"merger.store must be empty (SQLite) or postgresql://..., got "
                          f"{cfg.merger.store!r}")
    if not 0 < cfg.merger.lease_renew_s < cfg.merger.lease_s:
        raise ConfigError("merger.lease_renew_s must be in (0, merger.lease_s)")
    if (cfg.world.origin_lat_deg is None) != (cfg.world.origin_lon_deg is None):
        raise ConfigError("world.origin_lat_deg and world.origin_lon_deg go together: set both")
    bad = [v for v in cfg.grid.shard_map.values() if not 0 <= v < cfg.grid.shards]
    if bad:
        raise ConfigError(f"grid.shard_map names shards outside [0, {cfg.grid.shards}): {bad}")


def to_toml(obj, prefix: str = "") -> str:
    """Render a config as TOML (for `roadmap dump-config` and the effective config of a run)."""
    scalars, tables = [], []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            name = f"{prefix}{f.name}"
            tables.append(f"\n[{name}]\n" + to_toml(value, name + "."))
        else:
            scalars.append(f"{f.name} = {_toml_value(value)}")
    return "\n".join(scalars) + ("\n" if scalars else "") + "".join(tables)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f'"{k}" = {_toml_value(v)}' for k, v in value.items()) + "}"
    if value is None:
        return '""'
    return repr(value)
