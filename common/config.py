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


@dataclass(frozen=True)
class BusConfig:
    """How a process reaches Zenoh (a router's client by default; multicast scouting always off)."""

    mode: str = "client"
    connect: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    listen: list[str] = field(default_factory=list)
    lease_ms: int = 3000  # failure detection of hung processes (ZENOH.md 1.6)
    shared_memory: bool = False  # off: avoids zenoh#2628 (SHM query/reply drops under load)
    query_timeout_s: float = 5.0


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


@dataclass(frozen=True)
class RoiConfig:
    """IPM region of interest in the vehicle frame (paper: 12 m ahead x 8 m wide)."""

    x_min_m: float = 3.0
    length_m: float = 12.0
    width_m: float = 8.0


@dataclass(frozen=True)
class DemoConfig:
    """`roadmap demo` / `roadmap up`: drive lengths, segmenter, time limits of the local fleet."""

    segmenter: str = "truth"  # "truth" (corrupted true labels) or "onnx" (needs rendered images)
    images: bool = False  # render camera frames for the mapping drives (slow on 2 cores)
    max_km: float = 0.4  # length of each simulated drive
    small_max_km: float = 0.2  # --small (the localizer needs ~100 m to converge)
    drives: int = 1  # mapping drives per vehicle
    repaint_drives_before: int = 2  # per vehicle, old paint
    repaint_drives_after: int = 5  # single traversals after the repaint, one at a time
    repaint_min_km: float = 0.3  # repaint drives reach the moved line (120-250 m into the route)
    chaos_after_s: float = 0.0  # --chaos kills this long after the shard applied its first patch
    vehicle_timeout_s: float = 600.0
    localizer_timeout_s: float = 600.0
    # localize the production drive a second time on the uncompressed map (the codec's share
    # of the error, report.json localization.uncompressed_map)
    compare_raw_map: bool = True
    query_timeout_s: float = 5.0


@dataclass(frozen=True)
class SegmentationConfig:
    """Which segmenter runs on camera frames (common.segmentation.get_segmenter)."""

    kind: str = "onnx"  # "onnx" (the packaged model or model_path) | "truth" (simulated logs)
    model_path: str = ""  # empty: common/models/roadseg.onnx shipped with the package
    intra_op_threads: int = 1
    # rows above the rays that rise this many degrees above level (from the camera's
    # calibration) show no road and are not run through the network (labelled none); < 0:
    # every row is segmented; empty: the model's own (metadata `sky_margin_deg`), else
    # common.segmentation.DEFAULT_SKY_MARGIN_DEG. 10: the top 48 of 360 rows of the default
    # camera, 2.6 ms a frame less for an `s` network, its IoU moved by 0.0015 or less; a
    # network whose coarsest stage reads the whole frame (m64) asks for every row
    # (common/models/HISTORY.md)
    sky_margin_deg: float | None = None  # empty: the model's own, else 10 degrees
    # paint borders decided by the model's learned border classifier (metadata `border_net`,
    # common.segmentation.BorderNet), if it has one, instead of its brightness rule
    # (`refine`): on the benchmark's frames +0.0125 lane-line, +0.012 crosswalk, +0.017
    # stop-line IoU, for 1.3 ms a frame more at p50 (2 ms at p95); false: the rule
    border_net: bool = True
    # what the network does with the mirror image of a frame: "average" runs it on the image
    # and on its mirror and averages the two (twice the network's time: +0.011 mean lane-line
    # IoU on the benchmark's frames); "alternate" runs it once a frame, on the image and on
    # its mirror in turn (one run's cost; the car's mean errors 2-3 % above "average"'s over
    # 36 Karlsruhe drives, p95 14.4-15.1 ms on the AMX Xeon); "off" once on the image (the car
    # 6-9 % behind "average"); empty: the model's own (metadata `flip`, else `flip_average`)
    # (common/models/HISTORY.md, 2026-11-29 and before)
    flip: str = ""  # empty: the model's own; else off, average or alternate (FLIP_MODES)


@dataclass(frozen=True)
class LocalizerConfig:
    """User-end localizer: map access, point thinning, ICP, EKF, initialization."""

    map_codec: str = "contour"  # "contour" (compressed tiles) | "raw" (uncompressed, comparison)
    segmenter: str = "truth"  # "truth" (simulated logs: corrupted true labels) | "onnx"
    # "onnx": as vehicle.paint_min_margin, for ICP's points; 0: off (Karlsruhe 0.6 km drives,
    # seeds 1 / 2: 1 and 2 logits did not localize better than 0)
    paint_min_margin: float = 0.0  # logits a marking pixel's class must lead by to be a point
    ipm_stride: int = 2  # take every n-th pixel row and column of the label image
    max_points: int = 700  # points per frame into ICP
    road_fraction: float = 0.25  # share of road-surface points among them
    icp_iterations: int = 12
    icp_gate_start_m: float = 1.5
    icp_gate_end_m: float = 0.4
    icp_huber_m: float = 0.1
    icp_refine_iterations: int = 6  # sub-cell refinement on the lines' likelihood field (0: off)
    # lane-line likelihood field: the mask is widened by this square kernel (cells) before the
    # blur, a plateau instead of a sharp ridge (services/localizer/map_cache.py; Karlsruhe demo
    # drive, fleet map: 1 -> 5, x 0.075 -> 0.046 m, y 0.064 -> 0.027 m, yaw 0.152 -> 0.083 deg)
    field_line_grow_cells: int = 5
    # on a lane-lines-only match, hold the along-road position at the prediction with this
    # sigma (0: off) once the filter knows it to within hold_below_m (services/localizer/
    # localizer.py Localizer._held; Karlsruhe demo drive: x 0.046 -> 0.039 m, p90 0.093 -> 0.073)
    hold_along_road_m: float = 0.02
    hold_below_m: float = 0.1
    # one pixel of label noise at range r is r^2 / (f h) along the viewing ray: far points'
    # residuals along the ray weigh less (services/localizer/icp.py IpmNoise; 0: off; Karlsruhe
    # demo drive: x 0.039 -> 0.029, y 0.033 -> 0.027 m, yaw 0.087 -> 0.076 deg)
    ipm_sigma_px: float = 1.0
    icp_cov_scale: float = 60.0  # single-frame ICP is over-confident (correlated points, vibration)
    # (Karlsruhe drive, truth map: 30 -> x 0.078, y 0.114 m; 60 -> 0.070, 0.087; 120 -> 0.066,
    # 0.093)
    gnss_inflate: float = 1.5  # consumer GNSS has a slowly varying bias: trust it less
    speed_sigma_rel: float = 0.005  # the odometry scale itself is estimated
    # random walk of that scale (1/sqrt(s)): a wheel's scale error is all but constant; a faster
    # walk lets ICP's along-road errors, which follow the dash pattern, swing the scale by +-2 %
    # and the position saw-tooth with the dashes (Karlsruhe demo drive, fleet map: 1e-3 -> 3e-5,
    # longitudinal 0.070 -> 0.052 m, x 0.065 -> 0.050, y 0.058 -> 0.042 m)
    scale_walk_per_s: float = 3e-5
    yaw_rate_sigma_dps: float = 0.3
    max_position_sigma_m: float = 1.0  # integrity: ok False above this
    init_radius_m: float = 6.0  # coarse search half-size around the GNSS fix
    init_travel_m: float = 12.0  # metres of frames gathered before the coarse search
    init_frames: int = 30
    reinit_bad_frames: int = 30
    fetch_radius_m: float = 40.0  # tiles within this distance of the car are fetched
    prefetch_ahead_m: float = 60.0  # and these along the direction of travel
    cache_tiles: int = 25
    publish: bool = True  # publish roadmap/pose/<vehicle>
    recent_frames: int = 0  # also match a sample of the last n frames' points (odometry-chained)
    # use the filter's prediction as a prior inside ICP: a frame that barely constrains the
    # along-road position cannot walk along the lines (Karlsruhe drive: x 0.070 -> 0.062, y 0.087 ->
    # 0.051 m; town 0.066 -> 0.053, 0.082 -> 0.067 m)
    icp_prior: bool = True
    # first correspondence gate while tracking (init: icp_gate_start_m; the gate also grows with
    # the filter's position sigma): 1.5 m let a frame lock onto the next marking (Karlsruhe
    # drive: x error 0.114 -> 0.070 m)
    icp_track_gate_m: float = 0.5  # first correspondence gate while tracking, m
    # estimate the camera pitch per frame in ICP: 0.3 deg of vibration moves a point 12 m ahead
    # by 0.5 m (Karlsruhe drive: longitudinal error 0.124 -> 0.085 m mean)
    estimate_attitude: bool = True
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
    max_range_m: float = 11.0  # vote only ground points up to this far ahead (caps roi.length_m):
    # a 0.3 deg pitch vibration moves a ground point by range^2 / height x 0.005 (0.8 m at 15 m)
    upload_batch: int = 16  # patches per IngestBatch
    upload_timeout_s: float = 5.0  # per ingest query
    backoff_min_s: float = 0.05
    backoff_max_s: float = 2.0
    truth_seed: int = 0  # GroundTruthSegmenter corruption seed (deterministic re-mapping)
    # "onnx": marking pixels whose class leads the runner-up by less than this (logits) vote
    # nothing (common.segmentation min_margin). 120 town frames: false lane-line pixels 10 -> 7
    # % (2: 4 %), stop line 16 -> 10 % (6 %), keeping 92-99 % of the true ones (83-96 %); the
    # Karlsruhe demo maps (--small, seeds 0 / 1 / 3): lane-line precision 0.85 / 0.98 / 0.98 ->
    # 0.94 / 1.00 / 0.99 at recall 0.81 / 0.84 / 0.79 -> 0.80 / 0.81 / 0.78 (2: 0.79 / 0.78 /
    # 0.73, and the car localized worse on one drive). 0: the plain argmax
    paint_min_margin: float = 1.0  # logits a marking pixel's class must lead by to vote


@dataclass(frozen=True)
class MergerConfig:
    """Tile merger shard (services/merger): evidence rule, debounce, durability."""

    window_traversals: int = 3  # ballots of the newest observing traversals per cell (repaint in 2)
    footprint_cells: int = 9  # a traversal's unvoted cells inside its closed footprint vote none
    min_votes: int = 2  # votes behind a label, else unknown
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
    # OpenCV threads per shard process (0: OpenCV's default, one per core): a shard is one
    # core's work and more shards use more cores; N shards on N cores with N threads each
    # oversubscribe them (bench_merger: 2 shards on 2 cores ~5 % faster with 1)
    opencv_threads: int = 1


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


def _validate(cfg: RoadmapConfig) -> None:
    if cfg.grid.shards < 1:
        raise ConfigError("grid.shards must be >= 1")
    if cfg.bus.mode not in ("client", "peer", "router"):
        raise ConfigError(f"bus.mode must be client, peer or router, got {cfg.bus.mode!r}")
    if cfg.camera.width <= 0 or cfg.camera.height <= 0:
        raise ConfigError("camera.width and camera.height must be positive")
    if len(cfg.camera.dist) not in (4, 5, 8):
        raise ConfigError("camera.dist needs 4, 5 or 8 OpenCV coefficients")
    if cfg.segmentation.flip not in ("", *FLIP_MODES):
        raise ConfigError(f"segmentation.flip must be empty (the model's own) or one of "
                          f"{', '.join(FLIP_MODES)}, got {cfg.segmentation.flip!r}")
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
