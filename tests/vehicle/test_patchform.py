"""The vehicle's patch forms on a synthetic drive: the sparse form seals the cells form's patch
ids, its expanded patches merge to the cells form's map, and it travels through the outbox."""

import threading

import numpy as np
import pytest

from common.config import ConfigError, load_config
from common.drivelog import DriveLog
from common.evaluation import per_class_precision_recall
from common.messages import SparsePatch
from common.sparse import expand_patch
from services.merger.shard import MergerShard
from services.sim.truth_segmenter import GroundTruthSegmenter
from services.vehicle.mapper import VehicleMapper
from services.vehicle.node import StageTimer, build_mapper, map_log
from services.vehicle.outbox import Outbox
from services.vehicle.patchform import CellsForm, SparseForm, get_patch_form
from services.vehicle.synthetic import write_drive_log


class _Both:
    """The sparse form, keeping the cells patches it was given (the pairs to compare)."""

    def __init__(self, sparse_form):
        self.sparse, self.cells = sparse_form, []

    def finish(self, patches, poses):
        self.cells += patches
        return self.sparse.finish(patches, poses)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    root = tmp_path_factory.mktemp("drive") / "log"
    write_drive_log(root, np.random.default_rng(2), length_m=160.0, outage_m=(60.0, 100.0),
                    frame_stride=2)
    log = DriveLog(root)
    mapper = VehicleMapper(vehicle="map-0", traversal="d0", camera=log.meta.camera,
                           segmenter=GroundTruthSegmenter(seed=0), roi_x_min_m=3.0,
                           roi_length_m=8.0, roi_width_m=8.0, seal_every_frames=60)
    form = _Both(get_patch_form("sparse", ipm=mapper.ipm,
                                camera_x_m=log.meta.camera.T_vehicle_camera[0, 3],
                                roi_width_m=8.0))
    mapper.patch_form = form
    sparse = []
    map_log(log, mapper, sparse.extend, threading.Event(), StageTimer())
    return form.cells, sparse


def _map(patches) -> MergerShard:
    shard = MergerShard()
    shard.apply_batch(patches)
    shard.flush()
    return shard


def test_sparse_patches_keep_the_cells_forms_ids(drive):
    cells, sparse = drive
    assert len(sparse) == len(cells) > 3
    assert all(isinstance(s, SparsePatch) for s in sparse)
    assert [s.patch_id for s in sparse] == [c.patch_id for c in cells]
    assert [(s.t_first_ns, s.t_last_ns) for s in sparse] == [(c.t_first_ns, c.t_last_ns)
                                                            for c in cells]


def test_expanded_sparse_patches_merge_to_the_cells_forms_map(drive):
    """Per marking class and tile, the map of one drive in the sparse form against the cells
    form at 0.1 m: precision and recall >= 0.98 (1.00 measured)."""
    cells, sparse = drive
    a, b = _map(cells), _map([expand_patch(s) for s in sparse])
    assert a.tiles() == b.tiles()
    pred = np.concatenate([b.labels(t) for t in a.tiles()], axis=1)
    truth = np.concatenate([a.labels(t) for t in a.tiles()], axis=1)
    q = per_class_precision_recall(pred, truth)
    for name in ("lane_line", "stop_line"):
        assert q[name]["cells_true"] > 50
        assert q[name]["precision"] >= 0.98 and q[name]["recall"] >= 0.98, (name, q[name])


def test_sparse_patches_round_trip_the_outbox(drive, tmp_path):
    _, sparse = drive
    box = Outbox(tmp_path)
    box.put(sparse[:3])
    assert box.pending() == [s.patch_id for s in sparse[:3]]
    assert box.load(sparse[1].patch_id) == sparse[1]


def test_the_configured_form_is_built_and_checked(tmp_path):
    log_root = tmp_path / "log"
    write_drive_log(log_root, np.random.default_rng(0), length_m=30.0, frame_stride=4)
    log = DriveLog(log_root)
    cfg = load_config(env={}, sets=["segmentation.kind=truth"])  # the default: sparse
    mapper = build_mapper(log, "v", cfg)
    assert isinstance(mapper.patch_form, SparseForm)
    assert mapper.seal_every_frames == cfg.vehicle.sparse_seal_every_frames
    cells = load_config(env={}, sets=["vehicle.patch_form=cells", "segmentation.kind=truth"])
    mapper = build_mapper(log, "v", cells)
    assert isinstance(mapper.patch_form, CellsForm)
    assert mapper.seal_every_frames == cells.vehicle.seal_every_frames
    with pytest.raises(ConfigError, match="patch_form"):
        load_config(env={}, sets=["vehicle.patch_form=polygons"])
