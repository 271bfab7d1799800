"""The training loss's soft-Jaccard term, hard-pixel cross-entropy, mirror consistency and
distillation from a teacher, the moving average of the weights, bfloat16 training, and crops
then whole frames in one run (needs the optional torch extra: `.[train]`)."""

import functools
import json
from pathlib import Path

import numpy as np
import pytest

from common.classes import Cls
from common.segmentation import DEFAULT_MODEL

torch = pytest.importorskip("torch", reason="training tests need the .[train] extra (torch)")

from training.train import (  # noqa: E402
    WeightAverage,
    distillation_loss,
    hard_pixel_loss,
    mirror_consistency_loss,
    soft_jaccard_loss,
)

CLASSES = 7  # ours + the curb training class


def _confident(labels):
    """Logits that put all probability on `labels`."""
    return torch.nn.functional.one_hot(labels, CLASSES).permute(0, 3, 1, 2).float() * 40.0 - 20.0


def _line_frame():
    y = torch.full((1, 32, 32), int(Cls.ROAD))
    y[:, :, 15:17] = int(Cls.LANE_LINE)
    return y


def test_perfect_prediction_costs_almost_nothing_and_a_fattened_line_costs_its_iou():
    y = _line_frame()
    assert soft_jaccard_loss(_confident(y), y) < 0.02
    fat = y.clone()
    fat[:, :, 14:18] = int(Cls.LANE_LINE)  # predicted 4 px wide, true 2 px: IoU 0.5
    assert soft_jaccard_loss(_confident(fat), y) == pytest.approx(0.5, abs=0.02)


def test_classes_absent_from_the_truth_add_no_term():
    y = torch.full((1, 16, 16), int(Cls.ROAD))
    logits = torch.randn(1, CLASSES, 16, 16, requires_grad=True)
    loss = soft_jaccard_loss(logits, y)
    assert float(loss.detach()) == 0.0
    loss.backward()  # still a graph: a batch without paint trains on cross-entropy alone
    assert float(logits.grad.abs().sum()) == 0.0


def test_gradient_raises_the_missed_class_and_lowers_the_false_one():
    y = _line_frame()
    logits = torch.zeros(1, CLASSES, 32, 32, requires_grad=True)
    soft_jaccard_loss(logits, y).backward()
    g = logits.grad[0]
    assert float(g[Cls.LANE_LINE, 0, 15]) < 0.0  # descent raises lane line on the line
    assert float(g[Cls.LANE_LINE, 0, 0]) > 0.0  # and lowers it off the line


def test_hard_pixels_all_is_the_weighted_cross_entropy():
    y = _line_frame()
    logits = torch.randn(1, CLASSES, 32, 32)
    w = torch.linspace(1.0, 3.0, CLASSES)
    full = hard_pixel_loss(logits, y, w, 1.0, np.random.default_rng(0))
    per_px = torch.nn.functional.cross_entropy(logits, y, weight=w, reduction="none")
    assert float(full) == pytest.approx(float(per_px.mean()), rel=1e-5)


def test_hard_pixels_train_only_on_the_worst_share():
    y = _line_frame()  # 64 line pixels of 1024
    logits = _confident(y).clone()
    logits[:, :, :, 15] = 0.0  # one column of the line unsure: 32 hard pixels
    logits.requires_grad_(True)
    w = torch.ones(CLASSES)
    loss = hard_pixel_loss(logits, y, w, 32 / 1024, np.random.default_rng(0), sample=1024)
    assert float(loss.detach()) == pytest.approx(np.log(CLASSES), rel=1e-3)  # uniform: log C
    loss.backward()
    touched = logits.grad.abs().sum(1)[0] > 0
    assert bool(touched[:, 15].all()) and int(touched.sum()) == 32


def test_a_bad_hard_pixel_share_is_refused_before_rendering(tmp_path, capsys):
    from training.cli import main

    assert main(["train-seg", "--out", str(tmp_path), "--hard-pixels", "1.5"]) == 1
    assert "--hard-pixels must be a share in (0, 1]" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing rendered, nothing written


def test_mirror_consistency_is_zero_for_mirror_twins_and_pulls_both_to_their_average():
    torch.manual_seed(0)
    frames = torch.randn(2, CLASSES, 6, 10)
    twins = torch.cat([frames, frames.flip(-1)])  # each frame's mirror predicted as its mirror
    assert float(mirror_consistency_loss(twins)) < 1e-6
    # a mirror that disagrees costs; the gradient moves each side towards the other
    other = torch.randn(2, CLASSES, 6, 10)
    logits = torch.cat([frames, other]).requires_grad_(True)
    loss = mirror_consistency_loss(logits)
    assert float(loss) > 0.01
    loss.backward()
    step = logits.detach() - 0.5 * logits.grad
    assert float(mirror_consistency_loss(step)) < float(loss)


def test_mirror_consistency_needs_an_even_batch(tmp_path, capsys):
    from training.cli import main

    assert main(["train-seg", "--out", str(tmp_path), "--mirror-consistency", "1",
                 "--batch", "7"]) == 1
    assert "needs a weight >= 0 and an even --batch" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(tmp_path), "--mirror-consistency", "-1"]) == 1
    assert not any(tmp_path.iterdir())  # nothing rendered, nothing written


def test_a_run_by_steps_is_the_same_run_twice(tmp_path, frame_cache):
    """--steps: every frame rendered, the schedule spread over steps, not the machine's
    seconds: the same command gives the same file (here 48 frames, 100 steps: past the
    step-100 progress line). The second run reads the first's frames from the cache: the
    rendering's own determinism is test_training_data's."""
    from training.cli import main

    outs = []
    for name in ("a", "b"):
        out = tmp_path / name
        assert main(["train-seg", "--out", str(out), "--seed", "5", "--frames", "48",
                     "--steps", "100", "--batch", "1", "--workers", "1", *frame_cache]) == 0
        outs.append(out)
    log = json.loads((outs[0] / "train_log.json").read_text())
    assert log["steps"] == 100 and log["frames"] == 48
    assert "--steps 100" in log["command"] and "--minutes" not in log["command"]
    assert (outs[0] / "roadseg.onnx").read_bytes() == (outs[1] / "roadseg.onnx").read_bytes()
    assert len(list(Path(frame_cache[1]).glob("towns-*-s5-640x360-n48-*.npz"))) == 1  # --cache-dir


def test_a_soup_exports_the_average_of_its_runs(tmp_path, frame_cache):
    """--soup light,heavy: a run on each dose's towns, half the frames and steps each, and the
    export is their weights' mean (the head's bias aside: the offsets are calibrated on the
    average), as the two runs made alone give them."""
    from training.cli import main

    common = ["--seed", "5", "--batch", "1", "--workers", "1", *frame_cache]
    for name, soup, frames, steps in (("soup", "light,heavy", "48", "8"),
                                      ("light", "light", "24", "4"),
                                      ("heavy", "heavy", "24", "4")):
        assert main(["train-seg", "--out", str(tmp_path / name), "--frames", frames,
                     "--steps", steps, "--soup", soup, *common]) == 0
    log = json.loads((tmp_path / "soup" / "train_log.json").read_text())
    assert [(r["junctions"], r["steps"], r["frames"]) for r in log["soup"]] == [
        ("light", 4, 24), ("heavy", 4, 24)]
    assert "--soup light,heavy" in log["command"]
    assert "A soup of 2 runs" in (tmp_path / "soup" / "MODEL_CARD.md").read_text()
    soup, light, heavy = (torch.load(tmp_path / n / "roadseg.pt")["state"]
                          for n in ("soup", "light", "heavy"))
    assert not torch.equal(light["stem.0.weight"], heavy["stem.0.weight"])
    for name, value in soup.items():
        if value.is_floating_point() and name != "head.bias":
            torch.testing.assert_close(value, (light[name] + heavy[name]) / 2)


def test_average_init_exports_the_fine_tune_blended_with_its_start(tmp_path, frame_cache,
                                                                   s_export):
    """--average-init 0.25: the export is 0.75 x the trained weights + 0.25 x --init's (the
    head's bias aside: the offsets are calibrated on the blend); the trained ones are kept."""
    from training.archs import ARCHS
    from training.cli import main
    from training.data import TRAIN_CLASSES
    from training.net import RoadSegNet
    from training.train import _load_init

    init = s_export
    out = tmp_path / "wise"
    assert main(["train-seg", "--out", str(out), "--seed", "5", "--frames", "24", "--steps", "4",
                 "--batch", "1", "--workers", "1", *frame_cache, "--init", init,
                 "--average-init", "0.25"]) == 0
    log = json.loads((out / "train_log.json").read_text())
    assert log["average_init"] == 0.25 and "--average-init 0.25" in log["command"]
    start = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s"])
    assert _load_init(start, init)
    start = start.state_dict()
    trained = torch.load(out / "roadseg-trained.pt")["state"]
    blend = torch.load(out / "roadseg.pt")["state"]
    assert not torch.equal(trained["stem.0.weight"], start["stem.0.weight"])
    for name, value in blend.items():
        if value.is_floating_point() and name != "head.bias":
            torch.testing.assert_close(value, 0.75 * trained[name] + 0.25 * start[name])


def test_average_init_needs_init_and_a_weight_below_one(tmp_path, capsys):
    from training.cli import main

    out = tmp_path / "out"
    assert main(["train-seg", "--out", str(out), "--average-init", "0.5"]) == 1
    assert "--average-init: averages with --init's weights; give --init" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--average-init", "1",
                 "--init", str(DEFAULT_MODEL)]) == 1
    assert "the weight must be in [0, 1)" in capsys.readouterr().err
    assert not any(out.iterdir())  # nothing rendered, nothing written


def test_bad_soups_are_refused_before_rendering(tmp_path, capsys):
    from training.cli import main

    out = tmp_path / "out"
    assert main(["train-seg", "--out", str(out), "--soup", "light,wide"]) == 1
    assert "junction lines 'wide': one of light, heavy" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--soup", "light,heavy", "--ema", "0.9"]) == 1
    assert "--soup with --ema: leave one out" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--soup", "light,heavy", "--frames", "10"]) == 1
    assert "leaves under 8 frames" in capsys.readouterr().err
    weights = tmp_path / "weights.pt"
    weights.write_bytes(b"")
    assert main(["train-seg", "--out", str(out), "--soup", "light,heavy",
                 "--export-only", str(weights)]) == 1
    assert "with --export-only: give one dose" in capsys.readouterr().err
    assert not any(out.iterdir())  # nothing rendered, nothing written


def test_bad_steps_and_export_only_are_refused_before_rendering(tmp_path, capsys):
    from training.cli import main

    out = tmp_path / "out"
    assert main(["train-seg", "--out", str(out), "--steps", "0"]) == 1
    assert "--steps 0: at least 1" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--steps", "9", "--stream"]) == 1
    assert "would not be reproducible" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--export-only", "x.pt"]) == 1
    assert "--export-only x.pt: no such file" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--keep-offsets"]) == 1
    assert "give --export-only PT" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--set-flip", "alternate"]) == 1
    assert "give --reexport MODEL" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--no-cache", "--cache-dir", str(out)]) == 1
    assert "--cache-dir with --no-cache: leave one out" in capsys.readouterr().err
    assert not any(out.iterdir())  # nothing rendered, nothing written


def test_weight_average_weighs_steps_by_decay_and_not_the_starting_weights():
    model = torch.nn.Sequential(torch.nn.Linear(2, 1), torch.nn.BatchNorm1d(1))
    with torch.no_grad():
        model[0].weight.fill_(100.0)  # the starting weights: must count nothing
    average = WeightAverage(model, 0.5)
    for value in (1.0, 2.0, 4.0):
        with torch.no_grad():
            model[0].weight.fill_(value)
        model[1].num_batches_tracked.fill_(int(value))
        average.update(model)
    average.load_into(model)
    # weights 1/7, 2/7, 4/7 for the steps (decay 0.5, normalised by 1 - 0.5^3)
    expected = (1.0 * 0.25 + 2.0 * 0.5 + 4.0 * 1.0) / 1.75
    assert torch.allclose(model[0].weight, torch.full((1, 2), expected))
    assert int(model[1].num_batches_tracked) == 4  # integer buffers: the last step's


def test_weight_average_needs_an_update():
    with pytest.raises(ValueError, match="before any update"):
        WeightAverage(torch.nn.Linear(2, 1), 0.9).load_into(torch.nn.Linear(2, 1))


def test_an_ema_run_exports_the_average_and_its_last_weights_export_as_a_plain_run(
        tmp_path, frame_cache):
    """--ema exports the average and keeps the last step's weights; --export-only of those
    gives the very file the same run without --ema writes (the average draws no random
    numbers, and the export is the run's own)."""
    from training.cli import main

    run = ["--seed", "5", "--frames", "16", "--steps", "20", "--batch", "1", "--workers", "1",
           *frame_cache]
    ema, plain, last = tmp_path / "ema", tmp_path / "plain", tmp_path / "last"
    assert main(["train-seg", "--out", str(ema), *run, "--ema", "0.9"]) == 0
    assert main(["train-seg", "--out", str(plain), *run]) == 0
    assert main(["train-seg", "--out", str(last), *run,
                 "--export-only", str(ema / "roadseg-last.pt")]) == 0
    log = json.loads((ema / "train_log.json").read_text())
    assert log["ema"] == 0.9 and "--ema 0.9" in log["command"]
    assert "moving average" in (ema / "MODEL_CARD.md").read_text()
    assert (last / "roadseg.onnx").read_bytes() == (plain / "roadseg.onnx").read_bytes()
    assert (ema / "roadseg.onnx").read_bytes() != (plain / "roadseg.onnx").read_bytes()
    exported = json.loads((last / "export_log.json").read_text())
    assert exported["weights"].endswith("roadseg-last.pt") and exported["flip_average"]


def test_an_export_of_several_runs_is_the_export_of_their_averaged_weights(
        tmp_path, capsys, frame_cache):
    """--export-only A,B: the runs' weights averaged name by name, then exported as one run's
    (byte for byte the export of that average saved by hand); --soup DOSE calibrates on that
    dose's held-out frames, as a --soup DOSE run does (its own export, byte for byte)."""
    from training.cli import main
    from training.train import average_states

    run = ["--frames", "16", "--steps", "20", "--batch", "1", "--workers", "1", *frame_cache,
           "--soup", "heavy"]
    for name, seed in (("a", "5"), ("b", "6")):
        assert main(["train-seg", "--out", str(tmp_path / name), "--seed", seed, *run]) == 0
    a, b = (torch.load(tmp_path / n / "roadseg.pt") for n in ("a", "b"))
    torch.save({**a, "state": average_states([a["state"], b["state"]])}, tmp_path / "ab.pt")
    pts = f"{tmp_path / 'a' / 'roadseg.pt'},{tmp_path / 'b' / 'roadseg.pt'}"
    for name, weights in (("again", str(tmp_path / "a" / "roadseg.pt")), ("soup", pts),
                          ("by-hand", str(tmp_path / "ab.pt"))):
        assert main(["train-seg", "--out", str(tmp_path / name), "--seed", "5", *run,
                     "--export-only", weights]) == 0
    exported = {n: (tmp_path / n / "roadseg.onnx").read_bytes()
                for n in ("a", "again", "soup", "by-hand")}
    assert exported["again"] == exported["a"]
    assert exported["soup"] == exported["by-hand"] != exported["a"]
    log = json.loads((tmp_path / "soup" / "export_log.json").read_text())
    assert log["weights"] == pts and log["junctions"] == "heavy"
    torch.save({**a, "arch": {**a["arch"], "widths": [8, 16, 32, 64]}}, tmp_path / "other.pt")
    assert main(["train-seg", "--out", str(tmp_path / "bad"), "--seed", "5", *run,
                 "--export-only", f"{pts},{tmp_path / 'other.pt'}"]) == 1
    assert "is not of" in capsys.readouterr().err
    assert not any((tmp_path / "bad").iterdir())  # refused before rendering


def test_a_run_exported_again_with_its_offsets_and_a_streamed_run_on_its_held_out_frames(
        tmp_path, frame_cache):
    """--export-only PT --keep-offsets: a run's roadseg.pt, whose head carries its logit
    offsets, exported as that run did, byte for byte; with --stream, calibrated on the
    streamed run's held-out frames (the stream's first chunks, interleaved as train_model
    holds them); --reexport --set-flip sets what the runtime does with the mirror image
    (metadata `flip_average`, and `flip` for "alternate") and nothing else."""
    from training.cli import build_parser, main
    from training.data import SYNTH_SHARE, TURN_PROB, _render_chunk, _sim_available
    from training.train import STREAM_VAL_FRAMES, _metadata, streamed_held_out

    run = ["--seed", "5", "--frames", "16", "--steps", "20", "--batch", "1", "--workers", "1",
           *frame_cache, "--no-flip-average"]
    assert main(["train-seg", "--out", str(tmp_path / "a"), *run]) == 0
    weights = str(tmp_path / "a" / "roadseg.pt")
    assert main(["train-seg", "--out", str(tmp_path / "again"), *run, "--export-only",
                 weights, "--keep-offsets"]) == 0
    again = tmp_path / "again" / "roadseg.onnx"
    assert again.read_bytes() == (tmp_path / "a" / "roadseg.onnx").read_bytes()
    assert json.loads((tmp_path / "again" / "export_log.json").read_text())["logit_bias"] == (
        [0.0] * CLASSES)

    args = build_parser().parse_args(
        ["train-seg", "--seed", "5", "--frames", "48", "--stream", "--stream-junctions",
         "light,heavy"])
    args.turn_prob, args.synth_share = TURN_PROB, SYNTH_SHARE
    frames, labels = streamed_held_out(args)  # min(480, 48) frames at the start: 24 held out
    chunk, _ = _render_chunk((5, 0, (640, 360), _sim_available(), TURN_PROB, SYNTH_SHARE,
                              "light"))
    assert len(frames) == 24 < STREAM_VAL_FRAMES
    assert np.array_equal(frames, chunk[np.r_[0:24:2, 1:24:2]])
    assert main(["train-seg", "--out", str(tmp_path / "streamed"), "--seed", "5", "--frames",
                 "48", "--workers", "1", "--stream", "--stream-junctions", "light,heavy",
                 "--export-only", weights, "--keep-offsets"]) == 0
    log = json.loads((tmp_path / "streamed" / "export_log.json").read_text())
    assert log["frames"] == 24 and log["flip_average"]

    src = again
    for mode in ("average", "alternate", "off"):  # each re-exported from the one before
        assert main(["train-seg", "--out", str(tmp_path / mode), "--reexport", str(src),
                     "--set-flip", mode]) == 0
        src = tmp_path / mode / "roadseg.onnx"
    average, alternate, off = (_metadata(tmp_path / m / "roadseg.onnx")
                               for m in ("average", "alternate", "off"))
    assert average.pop("flip_average") is True and "flip" not in average
    assert alternate.pop("flip_average") is False and alternate.pop("flip") == "alternate"
    assert off.pop("flip_average") is False and "flip" not in off  # the mode removed again
    original = _metadata(again)
    assert original.pop("flip_average") is False
    assert average == alternate == off == original


def test_a_bad_ema_decay_is_refused_before_rendering(tmp_path, capsys):
    from training.cli import main

    assert main(["train-seg", "--out", str(tmp_path), "--ema", "1"]) == 1
    assert "--ema 1: the decay must be in [0, 1)" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_distillation_costs_least_where_the_student_says_what_the_teacher_says():
    """Cross-entropy against the teacher's probabilities is smallest at the teacher's own
    logits (Gibbs), whatever the labels, and the labels' class weights weigh the pixels."""
    gen = torch.Generator().manual_seed(0)
    teacher = torch.randn(2, CLASSES, 8, 16, generator=gen)  # at 1/2 resolution
    up = torch.nn.functional.interpolate(teacher, size=(16, 32), mode="bilinear",
                                         align_corners=False)
    y = torch.randint(0, CLASSES, (2, 16, 32), generator=gen)
    w = torch.ones(CLASSES)
    own = float(distillation_loss(up, teacher.half(), y, w))
    for _ in range(5):
        other = up + 0.5 * torch.randn(up.shape, generator=gen)
        assert float(distillation_loss(other, teacher.half(), y, w)) > own
    entropy = float(-(up.softmax(1) * up.log_softmax(1)).sum(1).mean())
    assert own == pytest.approx(entropy, abs=0.02)  # float16 targets
    heavy = w.clone()
    heavy[int(Cls.LANE_LINE)] = 6.0
    only_lines = torch.full_like(y, int(Cls.LANE_LINE))
    assert float(distillation_loss(up, teacher, only_lines, heavy)) == pytest.approx(
        float(distillation_loss(up, teacher, only_lines, w)))  # a weighted mean


def test_teacher_logits_are_the_flip_average_at_half_resolution():
    from training.archs import ARCHS
    from training.net import RoadSegNet
    from training.train import _frozen_copy, teacher_logits

    torch.manual_seed(0)
    teacher = _frozen_copy(RoadSegNet(num_classes=CLASSES, **ARCHS["s"]))
    x = torch.randint(0, 256, (3, 3, 64, 96), dtype=torch.uint8)
    got = teacher_logits(teacher, x, batch=2)
    assert got.dtype == torch.float16 and got.shape == (3, CLASSES, 32, 48)
    assert not teacher.half_res_logits  # the teacher is left as it was
    teacher.half_res_logits = True
    with torch.no_grad():
        f = x.float() / 255.0
        want = 0.5 * (teacher(f) + teacher(f.flip(-1)).flip(-1))
    torch.testing.assert_close(got.float(), want, atol=2e-2, rtol=1e-2)


def test_a_distilled_run_trains_towards_its_init_and_says_so(tmp_path, frame_cache, s_export):
    from training.cli import main

    out = tmp_path / "distil"
    assert main(["train-seg", "--out", str(out), "--seed", "5", "--frames", "24", "--steps", "4",
                 "--batch", "2", "--workers", "1", *frame_cache, "--init", s_export,
                 "--crop", "full", "--distill", "1", "--no-flip-average"]) == 0
    log = json.loads((out / "train_log.json").read_text())
    assert log["distill"] == 1.0 and "--distill 1" in log["command"]
    assert log["steps"] == 4 and np.isfinite(log["final_loss"])


def test_a_run_from_scratch_on_crops_distils_an_exported_teacher(tmp_path, frame_cache,
                                                                  s_export):
    """--teacher without --init, on random crops (the default): the teacher's logits are
    computed once per frame and cropped with each batch."""
    from training.cli import main

    out = tmp_path / "distil-crops"
    assert main(["train-seg", "--out", str(out), "--seed", "5", "--frames", "24", "--steps", "4",
                 "--batch", "2", "--workers", "1", *frame_cache, "--arch", "p16",
                 "--distill", "1", "--teacher", s_export, "--no-flip-average"]) == 0
    log = json.loads((out / "train_log.json").read_text())
    assert log["teacher"] == s_export and log["init"] is None
    assert log["crop_hw"] == [224, 384] and "--teacher" in log["command"]
    assert log["steps"] == 4 and np.isfinite(log["final_loss"])


def test_an_exported_teacher_gives_its_heads_flip_averaged_logits_through_onnxruntime(s_export):
    """--teacher: an export, run by onnxruntime, gives what the file's network loaded
    into torch gives: the flip-averaged logits of every trained class (the curb class too,
    before the export folds it into none), at 1/2 resolution, in float16."""
    from training.archs import ARCHS
    from training.net import RoadSegNet
    from training.train import (
        _frozen_copy,
        exported_model_like,
        onnx_teacher_logits,
        teacher_logits,
    )

    student = RoadSegNet(num_classes=CLASSES, **ARCHS["p16"])
    teacher = _frozen_copy(exported_model_like(s_export, student))
    x = (torch.rand(2, 3, 32, 640) * 255).to(torch.uint8)  # the export's width is fixed
    got = onnx_teacher_logits(s_export, x, threads=1)
    want = teacher_logits(teacher, x)
    assert got.dtype == torch.float16 and got.shape == (2, CLASSES, 16, 320)
    np.testing.assert_allclose(got.float().numpy(), want.float().numpy(), atol=0.02)
    assert not np.allclose(got[0].float().numpy(), got[1].float().numpy())


def test_distillation_needs_a_teacher_and_frames_at_the_start(tmp_path, capsys):
    from training.cli import main

    out = tmp_path / "out"
    assert main(["train-seg", "--out", str(out), "--distill", "1", "--crop", "full"]) == 1
    assert "--distill: distils --init's (or --teacher's) flip-averaged output" in (
        capsys.readouterr().err)
    assert main(["train-seg", "--out", str(out), "--teacher", str(DEFAULT_MODEL),
                 "--crop", "full"]) == 1
    assert "--teacher is the --distill teacher" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--distill", "1", "--crop", "full",
                 "--teacher", str(out / "absent.onnx")]) == 1
    assert "an exported RoadSegNet (.onnx) file" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--distill", "1", "--stream",
                 "--init", str(DEFAULT_MODEL)]) == 1
    assert "it cannot take --stream's frames" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--distill", "-1", "--crop", "full",
                 "--init", str(DEFAULT_MODEL)]) == 1
    assert "must be >= 0" in capsys.readouterr().err
    assert not any(out.iterdir())  # nothing rendered, nothing written


def test_a_distilled_run_refuses_odd_crops_before_rendering(tmp_path, capsys, monkeypatch):
    """The teacher's logits are at 1/2 resolution, so its crops need even sides; a run is told
    so before it renders a frame or computes a teacher's logits."""
    from training import data as seg_data
    from training.cli import main

    def no_rendering(**_):
        raise AssertionError("rendered frames before refusing the crop")

    monkeypatch.setattr(seg_data, "training_set", no_rendering)
    out = tmp_path / "out"
    for crop, message in (("385x224", "crops of 224x385: a teacher's 1/2-resolution logits"),
                          ("700x100", "--crop 700x100: outside the 640x360 frames")):
        assert main(["train-seg", "--out", str(out), "--distill", "1", "--crop", crop,
                     "--teacher", str(DEFAULT_MODEL), "--frames", "8", "--steps", "1"]) == 1
        assert message in capsys.readouterr().err


def test_a_bf16_run_trains_and_says_so(tmp_path, frame_cache, capsys):
    from training.cli import main
    from training.train import cpu_has_native_bf16

    out = tmp_path / "bf16"
    assert main(["train-seg", "--out", str(out), "--seed", "5", "--frames", "24", "--steps", "4",
                 "--batch", "2", "--workers", "1", *frame_cache, "--bf16",
                 "--no-flip-average"]) == 0
    log = json.loads((out / "train_log.json").read_text())
    assert log["bf16"] is True and "--bf16" in log["command"]
    assert "(bfloat16 autocast)" in (out / "MODEL_CARD.md").read_text()
    assert log["steps"] == 4 and np.isfinite(log["final_loss"])
    assert (out / "roadseg.onnx").stat().st_size > 10_000  # exported in float32
    # where torch emulates bfloat16 (no AVX-512 BF16 or AMX), the run says it is slower
    err = capsys.readouterr().err
    assert ("without native bfloat16" in err) == (not cpu_has_native_bf16())


def test_bf16_on_a_cpu_without_native_bfloat16_warns_that_it_is_slower():
    from training.train import bf16_warning, cpu_has_native_bf16

    warning = bf16_warning(True, "cpu", native=False)
    assert "--bf16" in warning and "float32's time" in warning
    assert bf16_warning(True, "cpu", native=True) is None
    assert bf16_warning(True, "cuda", native=False) is None  # GPUs have bfloat16 units
    assert bf16_warning(False, "cpu", native=False) is None
    # this machine's own answer, as the command asks it
    assert (bf16_warning(True, "cpu") is None) == cpu_has_native_bf16()


def test_full_after_trains_crops_then_whole_frames_and_says_so(tmp_path, monkeypatch, frame_cache):
    """--full-after 0.5: the first half of the steps on --crop's windows, the rest on whole
    frames (one run from scratch ending as the fine-tunes train), in the log and the card."""
    from training import train
    from training.cli import main

    windows = []
    crop_batch = train._crop_batch

    def recording(x, y, rng, crop_hw, half=None):
        windows.append(tuple(crop_hw))
        return crop_batch(x, y, rng, crop_hw, half)

    monkeypatch.setattr(train, "_crop_batch", recording)
    out = tmp_path / "full-after"
    assert main(["train-seg", "--out", str(out), "--seed", "5", "--frames", "24", "--steps", "4",
                 "--batch", "2", "--workers", "1", *frame_cache, "--full-after", "0.5",
                 "--no-flip-average"]) == 0
    assert windows == [(224, 384)] * 2 + [(360, 640)] * 2
    log = json.loads((out / "train_log.json").read_text())
    assert log["full_after"] == 0.5 and "--full-after 0.5" in log["command"]
    assert "crops for the first 50 % of the steps, whole frames after" in (
        out / "MODEL_CARD.md").read_text()


def test_full_after_needs_a_share_of_a_run_on_crops(tmp_path, capsys):
    from training.cli import main

    out = tmp_path / "out"
    for bad in ("0", "1.5", "-0.2"):
        assert main(["train-seg", "--out", str(out), "--full-after", bad]) == 1
        assert "a share of the run in (0, 1]" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--full-after", "0.5", "--crop", "full"]) == 1
    assert "--full-after with --crop full" in capsys.readouterr().err
    assert not any(out.iterdir())  # nothing rendered, nothing written


def test_train_model_itself_refuses_a_switch_it_cannot_make(tmp_path):
    """A caller of train_model (not only the command line) gets the same refusals: no switch
    to whole frames from whole-frame windows, no share outside (0, 1]."""
    from common.errors import ConfigError
    from training.train import train_model

    frames = np.zeros((8, 32, 64, 3), np.uint8)
    labels = np.zeros((8, 32, 64), np.uint8)
    for crop_hw, share in (((32, 64), 0.5), ((16, 32), 0.0), ((16, 32), 1.5)):
        with pytest.raises(ConfigError):
            train_model(frames, labels, tmp_path, seed=0, train_s=1.0, steps=1,
                        crop_hw=crop_hw, full_after=share)


def test_an_export_names_how_its_frames_differ_from_its_runs():
    """--export-only of a run's weights calibrates on the held-out frames of the command's own
    rendering settings; each setting that gives other frames than the run's is named (a
    --steps run's export without --steps rendered a new set under a budget, 2026-11-28)."""
    from argparse import Namespace

    from training.train import export_frame_differences

    run = {"seed": 3, "frames": 4800, "soup": [{"junctions": "heavy"}],
           "command": "roadmap train-seg --out DIR --seed 3 --steps 1200 --frames 4800"}

    def export(**kw):
        return Namespace(**{"seed": 3, "frames": 4800, "steps": 1200, "soup": ["heavy"], **kw})

    assert export_frame_differences(export(), run) == []
    assert export_frame_differences(export(steps=7), run) == []  # every frame rendered alike
    assert export_frame_differences(export(steps=None), run) == [
        "--steps given to the run, not to the export"]
    assert export_frame_differences(export(seed=4, frames=2400, soup=None), run) == [
        "--seed 4, the run's 3", "--frames 2400, the run's 4800",
        "junction lines light, the run's heavy (--soup DOSE)"]
    budgeted = {**run, "command": "roadmap train-seg --seed 3 --minutes 45"}
    assert export_frame_differences(export(), budgeted) == [
        "--steps given to the export, not to the run"]
    assert export_frame_differences(export(seed=9, steps=None, soup=None), {}) == []


def test_sky_cut_training_trains_on_the_rows_the_runtime_segments(tmp_path, monkeypatch,
                                                                   frame_cache):
    """--sky-cut-training with --sky-margin-deg 4: every batch is the frames without the 96
    top rows the runtime leaves out for the default camera at that margin (the rows' places in
    the frame kept for the row embedding), the held-out frames that set the logit offsets too;
    the log and the card say so, and the export names its margin."""
    from common.camera import camera_from_config
    from common.config import CameraConfig
    from common.segmentation import OnnxSegmenter
    from training import border, train
    from training.cli import main

    seen = []
    crop_batch = train._crop_batch

    def recording(x, y, rng, crop_hw, half=None):
        seen.append((tuple(x.shape[2:]), tuple(crop_hw)))
        return crop_batch(x, y, rng, crop_hw, half)

    calibrated = []
    calibrate_bias = train.calibrate_bias

    def calibrating(model, x_u8, y, rounds=2):
        calibrated.append(tuple(x_u8.shape[2:]))
        return calibrate_bias(model, x_u8, y, rounds)

    fitted = []  # the sky share the paint-border settings and the border classifier see
    for module, name in ((train, "calibrate_refine"), (border, "calibrate_border_net")):
        monkeypatch.setattr(module, name, functools.partial(
            lambda f, *a, sky_fraction=0.0, **k: fitted.append(sky_fraction) or f(
                *a, sky_fraction=sky_fraction, **k), getattr(module, name)))
    monkeypatch.setattr(train, "_crop_batch", recording)
    monkeypatch.setattr(train, "calibrate_bias", calibrating)
    out = tmp_path / "cut"
    assert main(["train-seg", "--out", str(out), "--seed", "5", "--frames", "24", "--steps", "2",
                 "--batch", "2", "--workers", "1", *frame_cache, "--crop", "full",
                 "--no-flip-average", "--sky-margin-deg", "4", "--sky-cut-training",
                 "--border-frames", "8", "--border-seed", "40"]) == 0
    seg = OnnxSegmenter(out / "roadseg.onnx", camera=camera_from_config(CameraConfig()))
    assert seg.sky_rows == 96
    assert seen == [((264, 640), (264, 640))] * 2 and calibrated == [(264, 640)]
    assert fitted == [96 / 360] * 2
    log = json.loads((out / "train_log.json").read_text())
    assert log["top_rows"] == 96 and "--sky-cut-training" in log["command"]
    assert "without their top 96 rows" in (out / "MODEL_CARD.md").read_text()
    # its weights exported again (--export-only) are calibrated on the same cut frames
    calibrated.clear()
    fitted.clear()
    assert main(["train-seg", "--export-only", str(out / "roadseg.pt"), "--out",
                 str(tmp_path / "again"), "--seed", "5", "--frames", "24", "--steps", "2",
                 "--workers", "1", *frame_cache, "--no-flip-average", "--sky-margin-deg", "4",
                 "--sky-cut-training"]) == 0
    assert calibrated == [(264, 640)] and fitted == [96 / 360]


def test_sky_cut_training_needs_a_margin(tmp_path, capsys):
    from training.cli import main

    out = tmp_path / "out"
    for margin in ([], ["--sky-margin-deg", "-1"]):
        assert main(["train-seg", "--out", str(out), "--sky-cut-training", *margin]) == 1
        assert "give --sky-margin-deg D (D >= 0)" in capsys.readouterr().err
    assert not any(out.iterdir())


def test_train_model_refuses_top_rows_it_cannot_cut(tmp_path):
    """Odd counts (a teacher's 1/2-resolution logits are cut with the frames), none left, or
    crops taller than what is left: refused before any step."""
    from common.errors import ConfigError
    from training.train import train_model

    frames = np.zeros((8, 32, 64, 3), np.uint8)
    labels = np.zeros((8, 32, 64), np.uint8)
    for top_rows, crop_hw in ((3, (32, 64)), (32, (32, 64)), (20, (16, 32))):
        with pytest.raises(ConfigError, match="top rows|do not fit"):
            train_model(frames, labels, tmp_path, seed=0, train_s=1.0, steps=1,
                        crop_hw=crop_hw, top_rows=top_rows)


def test_reexport_adds_logit_offsets_to_the_head(tmp_path, capsys):
    """--reexport --add-offsets lane_line=0.4: the new file's lane-line logits are the old
    ones + 0.4 and every other class's are the old ones; a class it cannot shift is refused
    before anything is written."""
    import onnxruntime as ort

    from common.classes import NUM_CLASSES
    from training.archs import ARCHS
    from training.cli import main
    from training.data import TRAIN_CLASSES
    from training.net import RoadSegNet
    from training.train import export_onnx

    torch.manual_seed(0)  # a file as the product's are exported: our six classes
    model = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s"]).eval()
    model.export_classes = NUM_CLASSES
    s_export = str(tmp_path / "roadseg.onnx")
    export_onnx(model, Path(s_export), seed=0)
    out = tmp_path / "shifted"
    assert main(["train-seg", "--out", str(out), "--reexport", s_export, "--add-offsets",
                 "lane_line=0.4,crosswalk=-0.25"]) == 0
    x = np.random.default_rng(3).random((1, 3, 64, 640), np.float32)
    (old,), (new,) = (ort.InferenceSession(str(p)).run(None, {"image": x})
                      for p in (s_export, out / "roadseg.onnx"))
    expected = old.copy()
    expected[:, Cls.LANE_LINE] += 0.4
    expected[:, Cls.CROSSWALK] -= 0.25
    np.testing.assert_allclose(new, expected, atol=1e-4)
    for bad in ("none=1", "lane=0.4", "lane_line", "lane_line=nan"):
        assert main(["train-seg", "--out", str(tmp_path / "bad"), "--reexport", s_export,
                     "--add-offsets", bad]) == 1
        assert "--add-offsets" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(tmp_path / "bad"), "--add-offsets",
                 "lane_line=0.4"]) == 1
    assert "give --reexport MODEL" in capsys.readouterr().err
    assert not any((tmp_path / "bad").iterdir())  # nothing written
