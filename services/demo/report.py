"""report.json of a demo run (DESIGN.md: Evaluation), assembled from what the services wrote in
OUT and the truth in the drive logs and the world; and the table printed next to the paper's
numbers. Functions over those outputs; the metrics are the evaluation harness's (services/eval).

OUT/run/tiles.npz: the merged tiles as fetched from the shards; OUT/run/<vehicle>/: each mapping
vehicle's STATE (services/vehicle/outputs.py); OUT/localizer/, OUT/localizer-raw/: the production
drive on the compressed and on the uncompressed map (services/localizer/outputs.py); OUT/drives/:
the drive logs, with their true poses."""

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.config import RoadmapConfig
from common.drivelog import DriveLog
from common.trajectory import read_tum
from services.demo.errors import DemoError
from services.demo.fetch import load_tiles
from services.eval import map as ev
from services.eval.localization import (
    LocalizedFrames,
    interp_poses,
    localization_section,
    localized_frames,
    pose_errors,
)
from services.eval.mapping import mapping_section as fleet_mapping_section
from services.eval.mapping import pose_errors as vehicle_pose_errors
from services.localizer.outputs import read_summary as read_localizer_summary
from services.vehicle.outputs import read_poses, read_summary

logger = logging.getLogger("roadmap.demo")

# The paper's numbers (Qin et al. 2021, Table I and Sec. V-B), for the printed comparison.
PAPER = {
    "x_m": {"mean": 0.043, "p90": 0.104},
    "y_m": {"mean": 0.040, "p90": 0.092},
    "yaw_deg": {"mean": 0.124, "p90": 0.240},
    "kb_per_km": 36.0,
}
# what the uncompressed-map run adds to the localization section
RAW_MAP_KEYS = ("x_m", "y_m", "yaw_deg", "lateral_m", "longitudinal_m", "availability_0_5m",
                "convergence_s", "tile_bytes")


@dataclass
class DemoOutputs:
    """What a demo run leaves for its report: OUT, and what only the orchestrator knows."""

    out: Path
    cfg: RoadmapConfig  # the fleet's config (every process got it)
    world: object  # the world of the production drive (after a repaint: the new paint)
    production_log: Path
    stats: dict  # the shards' counters after mapping: {"s<i>": counters or None}
    vehicles: list[tuple[Path, Path]]  # (STATE, drive log) per mapping vehicle, as they finished
    update: dict | None  # the repaint check (scenario repaint)
    settings: dict  # the run section's settings (seed, vehicles, shards, ...)
    chaos_events: list[dict]
    router: str | None
    takeover_s: float | None = None  # --store postgresql:// --chaos: the takeover's time


@dataclass
class MapRasters:
    """The merged map as mosaics: as voted (raw), decoded from its contours, the world's truth,
    and the area the mapping drives observed."""

    tiles: dict  # services.demo.fetch.load_tiles
    mosaic: ev.Mosaic
    raw: np.ndarray
    decoded: np.ndarray
    truth: np.ndarray
    observed: np.ndarray


@dataclass
class Track:
    """The localizer's TUM trajectory against the truth at its stamps (the figures)."""

    est_xy: np.ndarray
    truth_xy: np.ndarray
    errors: dict[str, np.ndarray]
    scored: np.ndarray  # the estimates the statistics are taken over


# -- the report ----------------------------------------------------------------------------------


def build_report(o: DemoOutputs, maps: MapRasters, frames: LocalizedFrames) -> dict:
    """Every section but timings and processes, in the contract's order."""
    drives = [_truth_xy(p.parent) for p in mapping_logs(o.out)]
    km_mapped = ev.km_mapped(drives)
    km_driven = sum(_path_km(xy) for xy in drives)  # the pipeline's upload per km
    summaries = vehicle_summaries(o)
    report = {
        "world": {"name": o.world.name, "km": round(float(o.world.km_of_road), 4),
                  "km_mapped": round(km_mapped, 4)},
        "map": map_section(maps, km_mapped),
        "segmentation": segmentation_section(o.cfg, o.production_log),
        "mapping": mapping_section(o, summaries),
    }
    if o.update is not None:
        report["update"] = o.update
    report["localization"] = localizer_section(o, frames)
    report["pipeline"] = pipeline_section(o.stats, summaries, km_driven)
    if o.takeover_s is not None:
        report["pipeline"]["takeover_s"] = o.takeover_s
    report["run"] = {**o.settings, "chaos_events": o.chaos_events,
                     "tile_versions": maps.tiles["versions"], "router": o.router}
    return report


def map_rasters(o: DemoOutputs, decode_tile) -> MapRasters:
    """The fetched tiles (OUT/run/tiles.npz) as mosaics, with the truth and the observed area."""
    t = load_tiles(o.out / "run" / "tiles.npz")
    if not t["tiles"]:
        raise DemoError("the shards hold no tiles after mapping (see OUT/logs)")
    mosaic = ev.Mosaic(t["tiles"])
    return MapRasters(
        tiles=t,
        mosaic=mosaic,
        raw=mosaic.paste(t["tiles"], t["raw"]),
        decoded=mosaic.paste(t["tiles"], [decode_tile(b) for b in t["compressed"]]),
        truth=ev.truth_mosaic(o.world, mosaic, t["tiles"]),
        observed=observed_area(o.cfg, mosaic, mapping_logs(o.out)),
    )


def map_section(maps: MapRasters, km_mapped: float) -> dict:
    t = maps.tiles
    sizes = ev.map_sizes(t["compressed"], t["raw"])
    km = max(km_mapped, 1e-9)
    per_class = ev.map_quality(maps.raw, maps.truth, maps.observed)
    for name, fid in ev.codec_fidelity(maps.decoded, maps.raw).items():
        per_class[name].update(fid)
    return {
        "kb_per_km": sizes["compressed_bytes"] / 1024 / km,
        "raw_kb_per_km": sizes["raw_sparse_bytes"] / 1024 / km,
        "png_kb_per_km": sizes["png_bytes"] / 1024 / km,
        "per_class": per_class,
        "digest": ev.map_digest(t["tiles"], t["raw"]),
        "tiles": len(t["tiles"]), "codecs": t["codecs"], **sizes,
        "notes": "kb_per_km divides by world.km_mapped (km of road the mapping drives "
                 "covered, each road once); recall counts the true cells the mapping drives' "
                 "cameras saw of their IPM ROI (the image's view, not the whole rectangle); "
                 "raw = sparse grid of 5 bytes per labelled cell; png = one PNG per tile",
    }


def segmentation_section(cfg: RoadmapConfig, log_path: Path, n_frames: int = 20) -> dict:
    """IoU of the segmenter the fleet used, on frames of the production drive, over the pixels
    of the mapping vehicles' IPM ROI (the only ones they turn into votes; the ONNX segmenter
    leaves the rows above it unsegmented: segmentation.roi_rows_only)."""
    from common.camera import build_ipm_lookup
    from common.segmentation import role_roi

    log = DriveLog(log_path)
    seg = fleet_segmenter(cfg, log.meta.camera)
    x_min_m, length_m, width_m = role_roi(cfg, "vehicle")
    ipm = build_ipm_lookup(log.meta.camera, x_min_m=x_min_m, length_m=length_m, width_m=width_m)
    inter, union, n_true, ms = np.zeros(6), np.zeros(6), np.zeros(6), []
    for i in np.linspace(0, len(log) - 1, min(n_frames, len(log))).astype(int):
        truth, image = log.labels(int(i)), log.image(int(i))
        t = time.perf_counter()
        pred = seg.segment(image, truth)
        ms.append((time.perf_counter() - t) * 1000.0)
        pred, truth = pred.reshape(-1)[ipm.pixel_index], truth.reshape(-1)[ipm.pixel_index]
        for c in range(2, 6):
            n_true[c] += np.sum(truth == c)
            inter[c] += np.sum((pred == c) & (truth == c))
            union[c] += np.sum((pred == c) | (truth == c))
    names = {2: "lane_line", 3: "stop_line", 4: "crosswalk", 5: "ground_sign"}
    return {"kind": cfg.segmentation.kind, "model": seg.name,
            "flip": getattr(seg, "flip", None), "first_row": getattr(seg, "first_row", None),
            "iou_pixels": "mapping vehicles' IPM ROI",
            "iou": {n: (float(inter[c] / union[c]) if n_true[c] else None)
                    for c, n in names.items()},
            "ms_p50": float(np.percentile(ms, 50)) if ms else None,
            "ms_p95": float(np.percentile(ms, 95)) if ms else None,
            "frames": len(ms)}


def fleet_segmenter(cfg: RoadmapConfig, camera=None):
    """The segmenter the fleet runs (common.segmentation.segmenter_for, the vehicles' role)."""
    from common.segmentation import segmenter_for

    return segmenter_for(cfg, "vehicle", camera=camera)


def vehicle_summaries(o: DemoOutputs) -> list[dict]:
    return [read_summary(state) for state, _ in o.vehicles]


def mapping_section(o: DemoOutputs, summaries: list[dict]) -> dict:
    """The vehicles' pose errors (their poses.npz vs their drive's truth), over the fleet."""
    errors = [vehicle_pose_errors(read_poses(state), DriveLog(log).streams["frame_pose_true"])
              for state, log in o.vehicles]
    return fleet_mapping_section(list(zip(summaries, errors, strict=True)),
                                 segmenter=o.cfg.segmentation.kind)


def localizer_frames(o: DemoOutputs, name: str = "localizer") -> LocalizedFrames:
    return localized_frames(o.out / name, DriveLog(o.production_log))


def localizer_section(o: DemoOutputs, frames: LocalizedFrames) -> dict:
    """The production drive on the compressed map; with demo.compare_raw_map, also the
    uncompressed one's errors."""
    loc = localization_section(frames, read_localizer_summary(o.out / "localizer"))
    if o.cfg.demo.compare_raw_map:
        raw_out = o.out / "localizer-raw"
        raw = localization_section(localizer_frames(o, "localizer-raw"),
                                   read_localizer_summary(raw_out))
        loc["uncompressed_map"] = {k: raw.get(k) for k in RAW_MAP_KEYS}
    return loc


def pipeline_section(stats: dict, summaries: list[dict], km_driven: float) -> dict:
    v = summaries
    shards = [c or {} for c in stats.values()]
    upload = sum(int(x.get("bytes_sent", 0)) for x in v)
    return {
        "upload_bytes": upload,  # every ingest request's payload, retries included
        "upload_kb_per_km_driven": round(upload / 1024 / km_driven, 2) if km_driven > 0 else None,
        "patches_sent": sum(int(x.get("patches_sent", 0)) for x in v),
        "patches_acked": sum(int(x.get("patches_acked", 0)) for x in v),
        "patches_applied": sum(int(c.get("patches_applied", 0)) for c in shards),
        "duplicates": sum(int(c.get("duplicates", 0)) for c in shards),
        "errors": sum(int(c.get("errors", 0)) for c in shards)
        + sum(int(x.get("errors", 0)) for x in v),
        "vehicle_duplicates": sum(int(x.get("duplicates", 0)) for x in v),
        "shards": {k: {n: c.get(n) for n in
                       ("patches_applied", "duplicates", "errors", "tiles", "digest")}
                   for k, c in stats.items() if c},
    }


def timings_section(wall_s: float, stage_ms: dict, summaries: list[dict]) -> dict:
    return {"wall_s": round(wall_s, 2),
            "per_stage_ms": {**stage_ms, "vehicle": vehicle_stage_ms(summaries)}}


def vehicle_stage_ms(summaries: list[dict]) -> dict:
    """Per-frame stage times of the mapping vehicles: {stage: {p50, p95}} averaged over them."""
    acc: dict[str, dict[str, list[float]]] = {}
    for s in summaries:
        for stage, v in (s.get("per_stage_ms") or {}).items():
            items = v.items() if isinstance(v, dict) else [("mean", v)]
            for k, x in items:
                if isinstance(x, int | float):
                    acc.setdefault(stage, {}).setdefault(k, []).append(float(x))
    return {st: {k: round(float(np.mean(v)), 3) for k, v in d.items()} for st, d in acc.items()}


# -- the repaint check ---------------------------------------------------------------------------


class RepaintCheck:
    """The update section of --scenario repaint: after the rounds of the old paint, the map after
    each traversal of the new paint, scored by how much of the new line and of the old one it
    shows (services.eval.map.follow_state), until it follows the repaint."""

    def __init__(self, before: dict, world_before, world_after, observed_area_of):
        """before: the tiles after the old paint (load_tiles); observed_area_of(mosaic): the
        cells the mapping drives observed."""
        if not before["tiles"]:
            raise DemoError("the shards hold no tiles after the rounds of the old paint")
        self.mosaic = ev.Mosaic(before["tiles"])
        old = ev.truth_mosaic(world_before, self.mosaic, before["tiles"])
        self.new_truth = ev.truth_mosaic(world_after, self.mosaic, before["tiles"])
        self.masks = ev.repaint_masks(old, self.new_truth, observed_area_of(self.mosaic))
        if not self.masks[0].any() or not self.masks[1].any():
            raise DemoError("the repainted lane line is outside the mapped area: choose another "
                            "--seed or a longer drive")
        self.snapshots = [("before repaint", paste_within(self.mosaic, before))]
        self.history: list[dict] = []
        self.followed_at: int | None = None

    def add(self, i: int, fetched: dict) -> dict:
        """The map after traversal i of the new paint (load_tiles) -> its follow state."""
        labels = paste_within(self.mosaic, fetched)
        state = ev.follow_state(labels, *self.masks)
        self.history.append({"traversal": i, **state})
        if i == 1 or state["followed"]:
            self.snapshots.append((f"after {i} traversal{'s' if i > 1 else ''}", labels))
        if state["followed"]:
            self.followed_at = i
        return state

    def strip(self) -> tuple[list, np.ndarray]:
        """(panels, focus) of figures.repaint_strip."""
        return (self.snapshots + [("new paint (ground truth)", self.new_truth)],
                self.masks[0] | self.masks[1])

    def section(self, traversals_before: int) -> dict:
        return {"traversals_to_follow": self.followed_at, "traversals_before": traversals_before,
                "repainted_cells": {"old_only": int(self.masks[0].sum()),
                                    "new_only": int(self.masks[1].sum())},
                "history": self.history, "rule": {"new_shown_min": ev.FOLLOW_NEW_MIN,
                                                  "old_shown_max": ev.FOLLOW_OLD_MAX}}


def paste_within(mosaic: ev.Mosaic, fetched: dict) -> np.ndarray:
    """The fetched tiles that fall inside `mosaic`, pasted (others dropped)."""
    keep = [i for i, (tx, ty) in enumerate(fetched["tiles"])
            if 0 <= tx - mosaic.tx0 < mosaic.ntx and 0 <= ty - mosaic.ty0 < mosaic.nty]
    return mosaic.paste([fetched["tiles"][i] for i in keep], [fetched["raw"][i] for i in keep])


# -- the drives' truth ---------------------------------------------------------------------------


def mapping_logs(out: Path) -> list[Path]:
    """log.json of every mapping drive of the run (before and after a repaint)."""
    return sorted(p for p in (out / "drives").glob("*/*/log.json")
                  if p.parent.parent.name != "production")


def observed_area(cfg: RoadmapConfig, mosaic: ev.Mosaic, log_jsons) -> np.ndarray:
    """Cells the mapping drives' cameras saw of their IPM ROI along their true poses."""
    roi, length_m = cfg.roi, cfg.roi.length_m
    if hasattr(cfg, "vehicle"):  # the vehicles vote only up to vehicle.max_range_m
        length_m = min(length_m, cfg.vehicle.max_range_m - roi.x_min_m)
    drives = []
    for p in log_jsons:
        log = DriveLog(p.parent if p.name == "log.json" else p)
        outline = ev.visible_outline(log.meta.camera, roi.x_min_m, length_m, roi.width_m)
        drives.append((log.streams["frame_pose_true"], outline))
    return ev.roi_footprint(mosaic, drives)


def _path_km(xy: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) / 1000.0 if len(xy) else 0.0


def _truth_xy(log_dir: Path) -> np.ndarray:
    s = DriveLog(log_dir).streams
    poses = s.get("truth_pose", s["frame_pose_true"])
    return poses[np.all(np.isfinite(poses), axis=1), :2]


# -- the trajectory figures' data ----------------------------------------------------------------


def localizer_track(o: DemoOutputs, frames: LocalizedFrames, convergence_s) -> Track | None:
    """OUT/localizer/trajectory.tum against the truth at its stamps; None without estimates."""
    tum = o.out / "localizer" / "trajectory.tum"
    if not tum.exists():
        logger.warning("no %s: skipping the trajectory figures", tum)
        return None
    t_ns_est, poses_est = read_tum(tum)
    est = np.column_stack([t_ns_est / 1e9, poses_est])
    log = DriveLog(o.production_log)
    t_ns = log.streams.get("truth_t_ns", log.streams["frame_t_ns"])
    poses = log.streams.get("truth_pose", log.streams["frame_pose_true"])
    if len(est) == 0:
        return None
    truth = interp_poses(est[:, 0], t_ns / 1e9, poses)
    return Track(est_xy=est[:, 1:3], truth_xy=truth[:, :2], errors=pose_errors(est[:, 1:], truth),
                 scored=scored_estimates(est[:, 0], frames, log.streams["frame_t_ns"],
                                         convergence_s))


def scored_estimates(t_est_s: np.ndarray, frames: LocalizedFrames, frame_t_ns: np.ndarray,
                     convergence_s) -> np.ndarray:
    """The estimates the report's statistics are taken over: on-map frames after convergence
    (all when no frame was localized)."""
    if len(frames.t_ns) == 0:
        return np.ones(len(t_est_s), dtype=bool)
    t_diag = frames.t_ns
    # nearest localized frame of each estimate (TUM times are float seconds)
    rel = t_est_s - int(t_diag[0]) * 1e-9
    k = np.clip(np.searchsorted((t_diag - t_diag[0]) * 1e-9, rel - 1e-3), 0, len(t_diag) - 1)
    t0 = (int(t_diag[0]) - int(frame_t_ns[0])) * 1e-9
    if convergence_s is None:
        after = np.zeros(len(k), dtype=bool)
    else:
        after = rel + t0 >= convergence_s - 1e-3
    return frames.on_map[k] & after


# -- the printed table ---------------------------------------------------------------------------


def _f(v, fmt="{:.3f}"):
    return "-" if v is None else fmt.format(v)


def format_table(report: dict) -> str:
    loc, m = report.get("localization", {}), report["map"]
    lines = [f"RoadMap demo: world {report['world']['name']} ({report['world']['km_mapped']:.2f} "
             f"km mapped), wall {report['timings']['wall_s']:.0f} s",
             f"{'':22s}{'ours mean':>10s}{'ours p90':>10s}{'paper mean':>12s}{'paper p90':>11s}"]
    lines += _localization_lines(loc)
    lines.append(f"{'map size [KB/km]':22s}{m['kb_per_km']:>10.1f}{'':10s}"
                 f"{PAPER['kb_per_km']:>12.1f}"
                 f"   (raw grid {m['raw_kb_per_km']:.0f}, PNG {m['png_kb_per_km']:.0f})")
    for name, c in m["per_class"].items():
        lines.append(f"  {name:20s}precision {_f(c['precision'], '{:.2f}')}  recall "
                     f"{_f(c['recall'], '{:.2f}')}  codec P/R "
                     f"{_f(c.get('codec_precision'), '{:.2f}')}"
                     f"/{_f(c.get('codec_recall'), '{:.2f}')}")
    p = report["pipeline"]
    lines.append(f"pipeline: sent {p['patches_sent']} acked {p['patches_acked']} applied "
                 f"{p['patches_applied']} duplicates {p['duplicates']} errors {p['errors']}; "
                 f"upload {_f(p.get('upload_kb_per_km_driven'), '{:.0f}')} KB per km driven")
    if "update" in report:
        n = report["update"]["traversals_to_follow"]
        lines.append(f"repaint: map followed after {n} traversals")
    lines.append(f"map digest {m['digest'][:16]}...  availability(0.5 m) "
                 f"{_f(loc.get('availability_0_5m'), '{:.2f}')}  convergence "
                 f"{_f(loc.get('convergence_s'), '{:.1f}')} s  segmenter "
                 f"{report['segmentation']['model']}")
    return "\n".join(lines) + "\n"


def _localization_lines(loc: dict) -> list[str]:
    lines = []
    rows = (("x_m", "x error [m]"), ("y_m", "y error [m]"), ("yaw_deg", "yaw error [deg]"))
    for key, label in rows:
        ours, paper = loc.get(key) or {}, PAPER[key]
        lines.append(f"{label:22s}{_f(ours.get('mean')):>10s}{_f(ours.get('p90')):>10s}"
                     f"{paper['mean']:>12.3f}{paper['p90']:>11.3f}")
    for key, label in (("lateral_m", "lateral [m]"), ("longitudinal_m", "longitudinal [m]")):
        ours = loc.get(key) or {}
        lines.append(f"{label:22s}{_f(ours.get('mean')):>10s}{_f(ours.get('p90')):>10s}")
    if "frames_on_map" in loc:
        every = loc.get("all_frames") or {}
        x_all, y_all = ((every.get(k) or {}).get("mean") for k in ("x_m", "y_m"))
        lines.append(
            f"  (on-map frames: {loc['frames_on_map']} of {loc.get('frames')}; all frames: x "
            f"{_f(x_all)}, y {_f(y_all)} m, availability "
            f"{_f(every.get('availability_0_5m'), '{:.2f}')})"
        )
    raw = loc.get("uncompressed_map")
    if raw:
        x, y, yaw = ((raw.get(k) or {}).get("mean") for k in ("x_m", "y_m", "yaw_deg"))
        lines.append(f"  (uncompressed map: x {_f(x)}, y {_f(y)} m, yaw {_f(yaw)} deg mean)")
    return lines
