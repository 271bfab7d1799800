"""The logit-offset calibration (training/train.py calibrate_bias): its search scores
every trial exactly as an argmax per trial does, ties included, and finds the offset that a
biased class needs."""

import numpy as np
import pytest

from common.classes import NUM_CLASSES, Cls
from training.train import BIAS_GRID, OffsetSearch

CLASSES = NUM_CLASSES + 1  # ours + the curb training class
PAINT = [int(Cls.LANE_LINE), int(Cls.STOP_LINE), int(Cls.CROSSWALK)]


def _argmax_score(logits, truth, bias, paint, fixed):
    """The score the search stands for: a full argmax (first maximum), the curb class as
    none, and each paint class's IoU over open and fixed pixels."""
    pred = (logits + np.asarray(bias, np.float32)).argmax(1)
    pred = np.where(pred >= NUM_CLASSES, 0, pred)
    ious = []
    for c in paint:
        inter = fixed[c][0] + int(((pred == c) & (truth == c)).sum())
        union = fixed[c][1] + int(((pred == c) | (truth == c)).sum())
        ious.append(inter / max(union, 1))
    return float(np.mean(ious))


@pytest.mark.parametrize("integer", [True, False])
def test_the_search_scores_each_trial_as_an_argmax_does(integer):
    """Integer logits and offsets tie often: an equal logit must go to the lower class, as
    argmax gives it. Real-valued ones check the grid the calibration uses."""
    rng = np.random.default_rng(3)
    n = 20_000
    truth = rng.integers(0, NUM_CLASSES, n)
    if integer:
        logits = rng.integers(-3, 4, (n, CLASSES)).astype(np.float32)
        values = np.arange(-3.0, 4.0)
    else:
        logits = rng.normal(0, 1, (n, CLASSES)).astype(np.float32)
        logits[np.arange(n), truth] += 0.8  # a model that is right more often than not
        values = BIAS_GRID
    fixed = {c: (int(rng.integers(0, 50)), int(rng.integers(50, 200))) for c in PAINT}
    search = OffsetSearch(logits, truth, PAINT, fixed)
    bias = [0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 2.0] if integer else [0.0, 0.0, 0.2, -0.4, 0.0, 0.0, 0.6]
    assert search.score(bias) == _argmax_score(logits, truth, bias, PAINT, fixed)
    for c in [*PAINT, NUM_CLASSES]:  # the paint classes and the curb class
        want = [_argmax_score(logits, truth, bias[:c] + [float(v)] + bias[c + 1:], PAINT, fixed)
                for v in values]
        assert search.scores_along(bias, c, values) == want
    with pytest.raises(ValueError, match="ascend"):
        search.scores_along(bias, PAINT[0], values[::-1])


def test_calibration_finds_the_offset_a_biased_class_lacks():
    """A model whose lane-line logit is 1.4 too low, so that road wins every lane-line pixel
    by 0.7: calibrate_bias raises it by the first grid step that gives them back (0.8), no
    more, leaves the classes it had right alone, and adds the offsets to the head's bias."""
    torch = pytest.importorskip("torch", reason="calibrate_bias runs a torch model (.[train])")
    from training.train import calibrate_bias

    rng = np.random.default_rng(0)
    y = torch.from_numpy(rng.choice([0, 1, 2, 3], (4, 16, 32), p=[0.3, 0.4, 0.2, 0.1]))
    frames = (torch.nn.functional.one_hot(y, CLASSES).permute(0, 3, 1, 2) * 255).to(torch.uint8)
    lane, road = int(Cls.LANE_LINE), int(Cls.ROAD)

    class Model(torch.nn.Module):  # each pixel's truth as a one-hot "image", read by a 1x1 head
        subpixel = 1

        def __init__(self):
            super().__init__()
            self.head = torch.nn.Conv2d(CLASSES, CLASSES, 1)
            with torch.no_grad():
                self.head.weight.copy_(torch.eye(CLASSES)[:, :, None, None] * 2.0)
                self.head.bias.zero_()
                self.head.bias[lane] = -1.4  # lane-line pixels: lane line 0.6, road 1.3
                self.head.weight[road, lane] = 1.3
                self.head.weight[lane, road] = 1.0  # road pixels: road 2, lane line -0.4

        def forward(self, x):
            return self.head(x)

    model = Model()
    assert not bool((model(frames.float() / 255.0).argmax(1) == lane).any())
    bias = calibrate_bias(model, frames, y)
    assert bias == [0.0, 0.0, 0.8, 0.0, 0.0, 0.0, 0.0]
    assert float(model.head.bias.detach()[lane]) == pytest.approx(-1.4 + 0.8)
    assert bool((model(frames.float() / 255.0).argmax(1) == y).all())
