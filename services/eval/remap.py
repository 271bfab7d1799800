"""An earlier run's map made again offline from its mapping drives' stored frames, with today's
mapper and segmenter: the loop to iterate the vehicle's side of the map on (the segmenter's
confidence gates, the frame minimums, the voting), paired by drive, as remerge.py is the
merger's and replay.py the car's.

Each mapping drive log (RUN/drives/<drive>/drives/<mapping>/<log>) keeps its camera frames and
sensor streams. Each is fed through the vehicle's own core (services.vehicle.node: build_mapper,
map_log: segmentation, IPM, pose graph, voting), in the order the logs are named, on today's
defaults with the run's segmentation and ROI (replay.stored_config) and `--set vehicle.KEY=VALUE`
(or segmentation., merger. ...). One MergerShard merges the patches, and the map is scored
against the world's truth as the demo's report scores it (services/eval/map.py: the same mosaic
of the run's tiles, the same observed area). With nothing changed this makes the run's map again
(the live suite at 97b896f: 0 cells differ on all 25 drives; `changed_cells` counts them). The
suite's ~41 000 mapping frames take 9 min on 2 cores instead of the suite's twenty minutes or
more. The car's figures stay the run's: the car localized on the run's map.

    roadmap eval --remap RUN --out DIR [--set vehicle.KEY=VALUE ...]"""

import threading
from pathlib import Path

from common.drivelog import DriveLog
from common.messages import GridPatch, SparsePatch
from common.sparse import expand_patch
from services.demo.report import mapping_logs
from services.eval.remerge import scored_map
from services.eval.replay import stored_config
from services.vehicle.node import StageTimer, build_mapper, map_log


def mapped_patches(log_dir: Path, cfg) -> list[GridPatch]:
    """Every patch the vehicle of one mapping drive log seals with config `cfg` (its id: the
    log's folder name, as `roadmap demo` names its vehicles)."""
    log = DriveLog(log_dir)
    mapper = build_mapper(log, log_dir.name, cfg)
    patches: list = []
    map_log(log, mapper, patches.extend, threading.Event(), StageTimer())
    # the cells and votes of a sparse/1 patch, as the shard derives them on ingest
    return [expand_patch(p) if isinstance(p, SparsePatch) else p for p in patches]


def remap_drive(drive_dir: Path, sets: list[str]) -> dict:
    """The map's per-class figures of the drive made again from its mapping drives with
    today's mapper and merger (+ sets), and how many cells differ from the run's map."""
    drive_dir = Path(drive_dir)
    cfg = stored_config(drive_dir, sets, role="fleet")
    logs = mapping_logs(drive_dir)
    patches = [p for log_json in logs for p in mapped_patches(log_json.parent, cfg)]
    return scored_map(drive_dir, patches, cfg.merger, cfg, logs) | {"patches": len(patches)}
