"""Pruning the 1/4-resolution channels of a trained RoadSegNet (training/prune.py;
needs the optional torch extra: `pip install .[train]`)."""

import json

import pytest

torch = pytest.importorskip("torch", reason="training tests need the .[train] extra (torch)")

from training import prune  # noqa: E402
from training.archs import ARCHS  # noqa: E402
from training.data import TRAIN_CLASSES  # noqa: E402
from training.net import RoadSegNet  # noqa: E402


def _folded_model(seed: int = 0):
    """A default-architecture network as an export loads: batch norms folded (scale 1, running
    mean 0, variance 1 - eps), their biases random, so a dropped channel must lose its bias."""
    torch.manual_seed(seed)
    model = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s"]).eval()
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.weight.fill_(1.0)
                m.bias.uniform_(0.1, 0.4)  # alive: no channel is dead by chance
                m.running_mean.zero_()
                m.running_var.fill_(1.0 - m.eps)
    return model


def test_a_masked_network_computes_what_the_narrowed_one_does():
    model = _folded_model()
    x = torch.rand(2, 3, 64, 96)
    enc_drop, dec_drop = [3, 14, 0, 19], [7, 1, 12, 5]
    enc = [c for c in range(20) if c not in enc_drop]
    dec = [c for c in range(20) if c not in dec_drop]
    narrowed = prune.narrowed_quarter(model, enc, dec)
    assert narrowed.arch["widths"] == [12, 16, 40, 64]
    with torch.no_grad():
        masked = prune.quarter_masked(model, enc_drop, dec_drop)(x)
        torch.testing.assert_close(narrowed(x), masked, atol=1e-5, rtol=1e-5)
        assert not torch.allclose(masked, model(x), atol=1e-3)  # the channels did matter
        keep_all = prune.narrowed_quarter(model, list(range(20)), list(range(20)))
        torch.testing.assert_close(keep_all(x), model(x), atol=1e-6, rtol=1e-6)
    with pytest.raises(ValueError, match="as many encoder as decoder"):
        prune.narrowed_quarter(model, enc, dec[:-1])


def _activations_zeroed(model, enc_drop, dec_drop):
    """`model` with the dropped channels zeroed in every feature map that holds them, as the
    network runs (forward hooks): an account of where the 1/4-resolution channels flow that
    knows nothing of the convolutions' weight indices (prune.quarter_channels). Encoder
    channels: down1's and enc1's outputs and the depthwise convolutions over them (enc1's,
    down2's, and dec1's over [upsampled 1/8, encoder]); decoder channels: dec1's output and
    dec0's depthwise convolution over [upsampled decoder, 1/2]."""
    w2 = model.arch["widths"][2]

    def zero(channels):
        def hook(module, inputs, output):
            output = output.clone()
            output[:, channels] = 0.0
            return output
        return hook

    enc = list(enc_drop)
    for module, channels in [(model.down1, enc), *[(b.dw, enc) for b in model.enc1],
                             *[(b, enc) for b in model.enc1], (model.down2.dw, enc),
                             (model.dec1.dw, [w2 + c for c in enc]), (model.dec1, dec_drop),
                             (model.dec0.dw, list(dec_drop))]:
        module.register_forward_hook(zero(channels))
    return model


def test_the_masked_network_is_the_network_without_those_channels():
    """The weights zeroed by the channel maps compute what the network computes with those
    channels' activations zeroed wherever they flow: the maps' wiring, checked against the
    network itself (a wrong offset in a concatenation reads a live channel)."""
    import copy

    model = _folded_model(2)
    x = torch.rand(2, 3, 64, 96)
    enc_drop, dec_drop = [2, 11, 19], [0, 8, 13]
    with torch.no_grad():
        masked = prune.quarter_masked(model, enc_drop, dec_drop)(x)
        hooked = _activations_zeroed(copy.deepcopy(model), enc_drop, dec_drop)(x)
        torch.testing.assert_close(masked, hooked, atol=1e-5, rtol=1e-5)
        assert not torch.allclose(masked, model(x), atol=1e-3)


def test_greedy_pruning_drops_dead_channels_first_and_keeps_the_width_asked():
    model = _folded_model(1)
    with torch.no_grad():  # decoder channel 9 and encoder channel 4 made dead
        dead = prune.quarter_masked(model, [4], [9])
    x = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        reference = dead(x)

    def change(m):
        with torch.no_grad():
            return float((m(x) - reference).abs().mean())

    enc, dec, steps = prune.greedy_quarter_pruning(dead, 17, change)
    assert steps[0][:2] == ("dec", 9) and steps[1][:2] == ("enc", 4)
    assert steps[0][2] == steps[1][2] == 0.0  # nothing changes
    assert len(enc) == len(dec) == 17 and 4 not in enc and 9 not in dec
    with pytest.raises(Exception, match="cannot prune 20 channels"):
        prune.greedy_quarter_pruning(dead, 21, change)


def test_the_prune_command_writes_an_init_for_the_narrower_architecture(
        tmp_path, monkeypatch, frame_cache, s_export):
    """On a few town frames: an export of the default architecture pruned to p16 and widened
    computes the pruned network (its loss is the last drop's), and a fine-tune starts from it
    with --arch p16."""
    from training.cli import main

    monkeypatch.setattr(prune, "PRUNE_FRAMES", 1)
    out = tmp_path / "pruned"
    assert main(["train-seg", "--prune", s_export, "--arch", "p16", "--out", str(out),
                 "--seed", "5", "--frames", "8", "--workers", "1", *frame_cache]) == 0
    log = json.loads((out / "prune_log.json").read_text())
    assert log["widths"] == [16, 16, 48, 64] and log["loss_frames"] == 1
    assert len(log["encoder_kept"]) == len(log["decoder_kept"]) == 16
    assert len(log["steps"]) == 8
    assert log["loss_after"] == pytest.approx(log["steps"][-1][2], abs=1e-4)
    first = (out / "roadseg.pt").read_bytes()
    tuned = tmp_path / "tuned"
    assert main(["train-seg", "--out", str(tuned), "--seed", "6", "--frames", "8", "--steps",
                 "2", "--batch", "2", "--workers", "1", *frame_cache, "--crop", "full",
                 "--init", str(out / "roadseg.pt"), "--arch", "p16", "--no-flip-average"]) == 0
    assert json.loads((tuned / "train_log.json").read_text())["arch"] == "p16"
    assert main(["train-seg", "--prune", s_export, "--arch", "p16", "--out", str(out),
                 "--seed", "5", "--frames", "8", "--workers", "1", *frame_cache]) == 0
    assert (out / "roadseg.pt").read_bytes() == first  # the same file again


def test_prune_refuses_what_it_cannot_do_before_rendering(tmp_path, capsys, s_export):
    from training.cli import main

    out = tmp_path / "out"
    assert main(["train-seg", "--prune", s_export, "--arch", "m", "--out", str(out)]) == 1
    assert "must be --arch s with its 1/4-resolution width changed" in capsys.readouterr().err
    assert main(["train-seg", "--prune", str(tmp_path / "none.onnx"), "--arch", "p16",
                 "--out", str(out)]) == 1
    assert "an exported RoadSegNet (.onnx) file" in capsys.readouterr().err
    assert not any(out.iterdir())  # nothing rendered, nothing written
