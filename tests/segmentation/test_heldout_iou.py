"""The packaged model on frames of a world it never saw (Karlsruhe, rendered by the simulator):
a floor well under the benchmark's targets, to catch a broken model, export or preprocessing."""

import pytest

from common.segmentation import DEFAULT_MODEL, get_segmenter

FLOORS = {"road": 0.85, "lane_line": 0.50, "crosswalk": 0.70, "stop_line": 0.60}  # measured 0.95 0.70 0.92 0.93


@pytest.mark.shared_data
@pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no packaged model yet")
def test_packaged_model_iou_floor_on_heldout_karlsruhe_frames(shared_data):
    from services.segtrain.evaluate import IouAccumulator, render_heldout

    osm = shared_data / "lanelet2-karlsruhe" / "mapping_example.osm"
    if not osm.is_file():
        pytest.skip("Karlsruhe Lanelet2 map missing")
    pairs, _ = render_heldout(f"lanelet2:{osm}", frames=8, seed=5, rare_prob=0.6)
    seg = get_segmenter("onnx", intra_op_threads=2)
    acc = IouAccumulator()
    for rgb, truth in pairs:
        acc.add(seg.segment(rgb), truth)
    iou = acc.result()
    for name, floor in FLOORS.items():
        if iou[name] is not None:
            assert iou[name] >= floor, f"{name} IoU {iou[name]:.3f} < {floor} ({iou})"
    assert iou["lane_line"] is not None
