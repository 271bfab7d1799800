"""RoadSegNet's row embedding, its half-resolution export and fine-tuning from a saved run
(needs the optional torch extra: `pip install .[train]`)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training tests need the .[train] extra (torch)")

from common.classes import NUM_CLASSES  # noqa: E402
from common.segmentation import OnnxSegmenter, session_metadata  # noqa: E402
from training import train  # noqa: E402
from training.archs import ARCHS  # noqa: E402
from training.data import TRAIN_CLASSES  # noqa: E402
from training.net import RoadSegNet, _row_features  # noqa: E402


def test_a_crop_sees_the_row_features_of_its_place_in_the_frame():
    frame = torch.zeros(1, 8, 360 // 8, 4)
    crop = torch.zeros(1, 8, 224 // 8, 4)
    top = 96  # a multiple of 16, as the training crops' feature rows line up with the frame's
    whole = _row_features(frame, 8, 0, 360)
    assert torch.allclose(_row_features(crop, 8, top, 360), whole[:, :, top // 8:top // 8 + 28])
    r = whole[0, 0, :, 0]
    assert -1.0 < float(r[0]) < -0.9 and 0.9 < float(r[-1]) < 1.0  # top .. bottom of the frame


def test_the_row_embedding_changes_the_output_with_the_crop_position():
    torch.manual_seed(0)
    model = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["m"]).eval()
    torch.nn.init.normal_(model.rows3.weight, std=1.0)
    x = torch.rand(1, 3, 64, 128)
    with torch.no_grad():
        model.crop_rows = (0, 360)
        high = model(x)
        model.crop_rows = (288, 360)
        low = model(x)
    assert not torch.allclose(high, low)
    flat = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s"]).eval()
    with torch.no_grad():
        flat.crop_rows = (0, 360)
        a = flat(x)
        flat.crop_rows = (288, 360)
        assert torch.equal(a, flat(x))  # no rows: position-blind, as before


def test_half_resolution_export_gives_the_labels_of_the_full_resolution_logits(tmp_path, rng):
    """The graph ends at 1/2 resolution; OnnxSegmenter's bilinear upsampling before its argmax
    gives the labels torch's in-graph upsampling gives."""
    torch.manual_seed(1)
    model = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["m"]).eval()
    model.export_classes = NUM_CLASSES
    image = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    with torch.no_grad():
        ref = model(torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0)
    path = tmp_path / "m.onnx"
    train.export_onnx(model, path, seed=1)
    seg = OnnxSegmenter(path)
    assert seg._session.get_outputs()[0].shape == [1, NUM_CLASSES, 180, 320]
    labels = seg.segment(image)
    assert labels.shape == (360, 640)
    assert (labels == ref[0].argmax(0).numpy()).mean() > 0.999


def test_the_export_folds_the_curb_class_into_none_without_a_reduction(tmp_path):
    """Channel 0 of the export is the larger of the none and curb logits; with one auxiliary
    class the graph takes it as it is (no ReduceMax over one channel: 0.3 ms a pass), and with
    two it still takes their larger."""
    import onnx

    torch.manual_seed(2)
    x = torch.rand(1, 3, 64, 128)
    for extra in (1, 2):
        model = RoadSegNet(num_classes=NUM_CLASSES + extra, **ARCHS["s"]).eval()
        with torch.no_grad():
            full = model(x)
            model.export_classes = NUM_CLASSES
            folded = model(x)
        torch.testing.assert_close(folded[:, 1:], full[:, 1:NUM_CLASSES])
        torch.testing.assert_close(folded[:, 0], full[:, [0, *range(NUM_CLASSES, NUM_CLASSES
                                                                    + extra)]].amax(1))
        path = tmp_path / f"fold{extra}.onnx"
        train.export_onnx(model, path, seed=0)
        ops = {node.op_type for node in onnx.load(str(path)).graph.node}
        assert ("ReduceMax" in ops) == (extra > 1)


def test_fine_tuning_starts_from_a_saved_run_of_the_same_architecture(tmp_path):
    torch.manual_seed(2)
    saved = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["m"])
    path = tmp_path / "roadseg.pt"
    torch.save({"arch": saved.arch, "state": saved.state_dict()}, path)
    model = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["m"])
    assert train._load_init(model, str(path)) is False  # batch norms as trained: not frozen
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(),
                                                 saved.state_dict().values(), strict=True))
    with pytest.raises(ValueError, match="architecture"):
        train._load_init(RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s"]), str(path))
    # a run that fine-tuned an export kept its folded norms frozen: so does its continuation
    torch.save({"arch": saved.arch, "state": saved.state_dict(), "frozen_norms": True}, path)
    assert train._load_init(model, str(path)) is True
    # and the run's card says which it was
    assert "norms kept frozen" in train._init_text({"init": "a.onnx", "frozen_norms": True})
    assert "norms training on" in train._init_text({"init": "a.pt", "frozen_norms": False})
    assert train._init_text({"init": None}) == ""


def test_subpixel_export_gives_full_resolution_labels_and_starts_as_its_init(tmp_path, rng):
    """A sub-pixel head (`s-sub`) initialised from a 1/2-resolution export is that model with
    nearest-neighbour upsampling; its own export is argmaxed per sub-pixel by OnnxSegmenter
    into the labels of torch's pixel_shuffle."""
    half_path = tmp_path / "half.onnx"
    half = _export_random(half_path, seed=3)
    sub = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s-sub"]).eval()
    train._load_init(sub, str(half_path))
    sub.export_classes = NUM_CLASSES
    sub_path = tmp_path / "sub.onnx"
    train.export_onnx(sub, sub_path, seed=3)
    seg = OnnxSegmenter(sub_path)
    assert seg.subpixel == 2
    assert seg._session.get_outputs()[0].shape == [1, NUM_CLASSES * 4, 180, 320]
    image = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    labels = seg.segment(image)
    x = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0
    with torch.no_grad():
        sub.half_res_logits = False
        ref = sub(x)[0].argmax(0).numpy()
        half_labels = half(x)[0].argmax(0).numpy()  # half_res_logits: set by its export
    assert labels.shape == (360, 640)
    assert (labels == ref).mean() > 0.999
    assert (labels == half_labels.repeat(2, 0).repeat(2, 1)).mean() > 0.999
    quarter = seg.segment_model_size(image, out_size=(160, 90))
    assert quarter.shape == (90, 160)
    assert (quarter == labels[::4, ::4]).mean() > 0.99


def test_a_widened_model_starts_as_the_narrower_model_it_is_fine_tuned_from():
    """`--arch w16 --init s.pt`: the new channels (the ones onnxruntime's blocked convolutions
    pad to anyway) start random but ignored, so the wider model computes the narrower one."""
    from training.net import widen

    small = _random_model(4)
    wide = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["w16"]).eval()
    widen(small, wide)
    wide.export_classes = NUM_CLASSES
    x = torch.rand(2, 3, 96, 160)
    with torch.no_grad():
        assert torch.allclose(wide(x), small(x), atol=1e-4)
        assert wide.stem[0].weight[12:].abs().sum() > 0  # new channels are not dead
        assert not wide.head.weight[:, 12:].any()  # and not yet read
    with pytest.raises(ValueError, match="cannot widen"):
        widen(wide, RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s"]))


def test_an_export_pads_its_channels_to_16_and_loads_into_either_width(tmp_path, rng):
    """export_onnx writes `s` as [16, 32, 48, 64] with zero padding channels (net.aligned:
    onnxruntime keeps its blocked layout), computing what `s` computes; `--init` of that file
    narrows it back into `s` or loads it into `w16`; a file that uses its extra channels does
    not narrow."""
    import onnx
    import onnxruntime as ort

    from training.net import onnx_widths

    small = _random_model(4)
    path = tmp_path / "s.onnx"
    train.export_onnx(small, path, seed=4)
    assert onnx_widths(path) == ARCHS["w16"]["widths"]
    # the decoder blocks read their two inputs without a concatenation (onnx_graph)
    graph = onnx.load(str(path)).graph
    concatenated = {n.output[0] for n in graph.node if n.op_type == "Concat"}
    assert not [n for n in graph.node if n.op_type == "Conv" and n.input[0] in concatenated]
    assert sum("/split" in n.name for n in graph.node if n.op_type == "Conv") == 12
    session = ort.InferenceSession(str(path))
    meta = session_metadata(session)
    assert meta["arch"]["widths"] == ARCHS["w16"]["widths"]
    x = torch.from_numpy(rng.random((1, 3, 96, 640), np.float32))  # the export: 640 wide
    got = session.run(None, {"image": x.numpy()})[0]
    small.half_res_logits = True  # (as the export has it: logits at 1/2)
    with torch.no_grad():
        assert np.abs(small(x).numpy() - got).max() < 1e-4
    small.half_res_logits = False
    for arch in ("s", "w16"):
        model = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS[arch]).eval()
        assert train._load_init(model, str(path)) is True  # folded batch norms: kept frozen
        model.eval()
        model.export_classes = NUM_CLASSES
        with torch.no_grad():
            assert torch.allclose(model(x), small(x), atol=1e-4)
    used = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["w16"]).eval()
    torch.nn.init.normal_(used.head.weight)  # reads every channel of the 1/2 stage
    used_path = tmp_path / "used.onnx"
    used.export_classes = NUM_CLASSES
    train.export_onnx(used, used_path, seed=0)
    with pytest.raises(train.ConfigError, match="--arch"):
        train._load_init(RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s"]), str(used_path))


def test_an_export_aligned_to_8_channels_pads_less_and_computes_the_same(tmp_path, rng):
    """block=8 (AVX2's blocked convolutions; training/bench/archs.py) rounds `s` [12, 20, 40, 64]
    up to [16, 24, 40, 64], not to 16's [16, 32, 48, 64], and the file computes what `s` does."""
    import onnxruntime as ort

    from training.net import onnx_widths

    small = _random_model(5)
    path = tmp_path / "s8.onnx"
    train.export_onnx(small, path, seed=5, block=8)
    assert onnx_widths(path) == [16, 24, 40, 64]
    x = torch.from_numpy(rng.random((1, 3, 96, 640), np.float32))
    got = ort.InferenceSession(str(path)).run(None, {"image": x.numpy()})[0]
    small.half_res_logits = True
    with torch.no_grad():
        assert np.abs(small(x).numpy() - got).max() < 1e-4


def test_an_export_has_a_dynamic_height_and_a_re_export_keeps_the_model(tmp_path, rng):
    """export_onnx leaves the input height dynamic (OnnxSegmenter's sky rows); --reexport
    writes an older file again with the same weights and metadata."""
    import onnx

    path = tmp_path / "a.onnx"
    model = _export_random(path, seed=5)
    train.set_metadata(path, refine={"window": 7, "level": 0.5})
    # an older, fixed-height file: the same graph with the height pinned
    proto = onnx.load(str(path))
    assert proto.graph.input[0].type.tensor_type.shape.dim[2].dim_param == "height"
    proto.graph.input[0].type.tensor_type.shape.dim[2].dim_value = 360
    old = tmp_path / "old.onnx"
    onnx.save(proto, str(old))
    got = train.reexport_onnx(old, tmp_path / "new" / "roadseg.onnx")
    assert got["max_abs_diff"] < 1e-4 and got["argmax_agreement"] == 1.0
    new = OnnxSegmenter(tmp_path / "new" / "roadseg.onnx", sky_fraction=0.3)
    assert new.refine == {"window": 7, "level": 0.5} and new.sky_rows == 96
    image = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    model.half_res_logits = False  # (export_onnx set it) logits upsampled as the runtime does
    with torch.no_grad():
        ref = model(torch.from_numpy(image[96:].transpose(2, 0, 1)[None] / 255.0).float())
    assert (new.segment(image)[96:] == ref.argmax(1)[0].numpy()).mean() > 0.999
    with pytest.raises(train.ConfigError, match="not a RoadSegNet"):
        bare = onnx.load(str(old))
        del bare.metadata_props[:]
        onnx.save(bare, str(tmp_path / "bare.onnx"))
        train.reexport_onnx(tmp_path / "bare.onnx", tmp_path / "x.onnx")


def _export_random(path, *, seed: int):
    """A randomly initialised RoadSegNet `s` exported to `path` (-> the torch model)."""
    model = _random_model(seed)
    train.export_onnx(model, path, seed=seed)
    return model


def _random_model(seed: int):
    """A randomly initialised RoadSegNet `s` (eval mode, auxiliary classes folded for export),
    with distinct batch-norm shifts (the export shares equal initializers, which loading
    cannot tell apart)."""
    torch.manual_seed(seed)
    model = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s"]).eval()
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            torch.nn.init.normal_(m.bias, 0.0, 0.1)
    model.export_classes = NUM_CLASSES
    return model
