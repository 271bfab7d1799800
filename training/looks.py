"""Training looks shared by both training renderers (training/synth.py and the simulator's
frames in training/data.py)."""

# Share of training looks whose curb faces are sunlit (the renderers' own looks: 20 %). On the
# Karlsruhe frames, 55 k of the 67 k false lane-line pixels lay on the curbs of the 4 looks (of
# 10) with sunlit faces, where the curb (face and top, ~180 grey) is brighter than the worn paint
# (~105-160): the model had learnt "the brightest band at the road's edge is paint".
SUNLIT_CURB = 0.5


def curb_face_gain(rng) -> float:
    """A training look's curb-face brightness relative to the curb top: sunlit (1.0-1.2) with
    SUNLIT_CURB, else in shade (0.35-0.75); for both renderers' looks."""
    return rng.uniform(1.0, 1.2) if rng.random() < SUNLIT_CURB else rng.uniform(0.35, 0.75)
