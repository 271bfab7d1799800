"""One default per setting: a component built with no overrides is the one its factory builds
from the default config (common.config), so a test's component is the product's.

Each case compares the public state of the two objects, nested components of ours included
(their private and foreign parts, such as onnxruntime or gtsam handles, only by type)."""

import dataclasses
import inspect
from collections import deque
from types import SimpleNamespace

import numpy as np
import pytest

from common import sparse
from common.camera import camera_from_config
from common.config import (
    BusConfig,
    CameraConfig,
    LocalizerConfig,
    MergerConfig,
    RoadmapConfig,
)
from common.segmentation import (
    DEFAULT_MODEL,
    OnnxSegmenter,
    roi_first_row,
    role_roi,
    segmenter_for,
    symbol_margins,
)
from services.localizer.ekf import PoseFilter
from services.localizer.icp import Icp
from services.localizer.init import CoarseSearch
from services.localizer.localizer import Localizer, get_localizer
from services.localizer.map_cache import TileCache, get_tile_cache
from services.localizer.tiles import TileClient
from services.merger.node import MergerNode
from services.merger.shard import MergerShard
from services.merger.store import ShardStore
from services.sim.truth_segmenter import GroundTruthSegmenter
from services.vehicle.mapper import VehicleMapper
from services.vehicle.node import build_mapper
from services.vehicle.patchform import SparseForm


def _ours(obj) -> bool:
    return type(obj).__module__.split(".")[0] in ("common", "services") and hasattr(obj, "__dict__")


def assert_same(a, b, where: str = "") -> None:
    """a and b hold the same public state, recursively through our own objects."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, np.ndarray):
        assert a.shape == b.shape and np.array_equal(a, b), where
    elif isinstance(a, deque):
        assert a.maxlen == b.maxlen, f"{where}.maxlen: {a.maxlen} != {b.maxlen}"
        assert_same(list(a), list(b), where)
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif _ours(a):
        for name, value in vars(a).items():
            if not name.startswith("_") and not callable(value):
                assert_same(value, vars(b)[name], f"{where}.{name}")
    elif isinstance(a, int | float | str | bool | type(None)):
        assert a == b or (a != a and b != b), f"{where}: {a!r} != {b!r}"  # NaN == NaN


@pytest.fixture(scope="module")
def camera():
    return camera_from_config(CameraConfig())


def test_a_default_localizer_is_the_product_localizer():
    cache = TileCache()
    product = get_localizer(LocalizerConfig(), cache)
    default = Localizer(cache, icp=Icp(), ekf=PoseFilter(), search=CoarseSearch())
    assert_same(default, product, "Localizer")


def test_a_default_tile_cache_is_the_product_tile_cache():
    assert_same(TileCache(), get_tile_cache(LocalizerConfig()), "TileCache")


class _Log:
    """What build_mapper reads of a DriveLog (no frames: camera images assumed)."""

    def __init__(self, camera):
        self.meta = SimpleNamespace(traversal="d0", camera=camera)

    def __len__(self):
        return 0


def _truth_config() -> RoadmapConfig:
    base = RoadmapConfig()
    return dataclasses.replace(base, segmentation=dataclasses.replace(base.segmentation,
                                                                     kind="truth"))


def test_a_default_vehicle_mapper_is_the_product_mapper(camera):
    cfg = _truth_config()  # the mapper's own defaults (the ONNX segmenter: below)
    product = build_mapper(_Log(camera), "veh-0", cfg)
    roi = cfg.roi  # required: the ROI's length follows from roi and vehicle.max_range_m
    default = VehicleMapper(
        vehicle="veh-0", traversal="d0", camera=camera,
        segmenter=GroundTruthSegmenter(seed=cfg.vehicle.truth_seed),
        roi_x_min_m=roi.x_min_m, roi_length_m=cfg.vehicle.max_range_m - roi.x_min_m,
        roi_width_m=roi.width_m, seal_every_frames=cfg.vehicle.sparse_seal_every_frames,
    )  # the default patch form is sparse/1, sealed every sparse_seal_every_frames
    default.patch_form = SparseForm(sparse.roi_of_lookup(
        default.ipm.ground_xy_m, camera_x_m=float(camera.T_vehicle_camera[0, 3]),
        width_m=roi.width_m))
    assert_same(default, product, "VehicleMapper")


def test_a_default_merger_shard_is_the_product_shard():
    def owns(tile):
        return True

    assert_same(MergerShard(owns=owns), MergerShard.from_config(MergerConfig(), owns),
                "MergerShard")


@pytest.mark.parametrize("role", ["vehicle", "localizer"])
def test_the_truth_segmenter_of_each_role(role):
    """The corruption seed is the role's own (vehicle.truth_seed, localizer.truth_seed)."""
    cfg = _truth_config()
    seed = getattr(cfg, role).truth_seed
    assert segmenter_for(cfg, role) == GroundTruthSegmenter(seed=seed)


@pytest.mark.skipif(not DEFAULT_MODEL.exists(), reason="packaged model missing")
def test_a_default_onnx_segmenter_is_the_product_segmenter(camera):
    """The default segmenter is the model. The confidence gate is the role's own: the car's
    (localizer.paint_min_margin) is OnnxSegmenter's default, the plain argmax; the mapping
    vehicles' is passed. Each role segments from the first row of its own IPM ROI."""
    cfg = RoadmapConfig()
    assert cfg.segmentation.kind == "onnx"
    car_row = roi_first_row(camera, *role_roi(cfg, "localizer"))
    assert_same(OnnxSegmenter(camera=camera, first_row=car_row, flip=cfg.segmentation.flip),
                segmenter_for(cfg, "localizer", camera=camera), "OnnxSegmenter")
    vehicle = OnnxSegmenter(camera=camera, min_margin=cfg.vehicle.paint_min_margin,
                            flip=cfg.segmentation.flip,
                            class_min_margin=symbol_margins(cfg, "vehicle"),
                            first_row=roi_first_row(camera, *role_roi(cfg, "vehicle")))
    assert_same(vehicle, segmenter_for(cfg, "vehicle", camera=camera), "OnnxSegmenter")


def _default(cls, name):
    return inspect.signature(cls).parameters[name].default


def test_the_node_adapters_default_to_the_config_values_their_nodes_pass():
    """Built inline by their nodes (a session or a file behind them): constructor defaults."""
    lc, bus, mc = LocalizerConfig(), BusConfig(), MergerConfig()
    assert _default(TileClient, "codec_name") == lc.map_codec
    assert _default(TileClient, "timeout_s") == bus.query_timeout_s
    assert _default(ShardStore, "synchronous") == mc.sqlite_synchronous
    for name in ("debounce_s", "debounce_max_s", "ingest_queue", "ingest_group"):
        assert _default(MergerNode, name) == getattr(mc, name), name
