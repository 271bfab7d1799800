"""Score utilities of the segmentation runtime: per-class logits (C, h, w) upsampled at chosen
pixels, argmaxed, mirrored, and the confidence (lead over the runner-up)."""


import cv2
import numpy as np


def rows_below(score_at, rows: int, ys, xs):
    """score_at of labels that gained `rows` rows on top (the sky rows)."""
    return score_at(np.asarray(ys) - rows, xs)


def lead_of(scores: np.ndarray) -> np.ndarray:
    """(N,): how far the best of (C, N) scores leads the runner-up (C >= 2; 0 where two
    share the best). Row maxima, not np.partition along axis 0: 3x faster."""
    best = scores.max(axis=0)
    hit = scores == best
    lead = best - np.where(hit, -np.inf, scores).max(axis=0)
    lead[hit.sum(axis=0) > 1] = 0.0
    return lead


def scores_at(scores: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """(C, N) scores of (C, H, W) `scores` at pixels (ys, xs)."""
    return scores[:, ys, xs]


def subpixel_scores_at(scores: np.ndarray, s: int, ys: np.ndarray, xs: np.ndarray,
                        scale: tuple[float, float] = (1.0, 1.0)):
    """(C, N) scores of sub-pixel logits (C * s * s, h, w) at full-resolution pixels (ys, xs);
    with `scale` (full-resolution rows, columns per label pixel), at label pixels of a nearest
    resize of the full-resolution labels (as cv2.INTER_NEAREST picks: floor(y * scale))."""
    if scale != (1.0, 1.0):
        ys = np.minimum((ys * scale[0]).astype(np.int64), s * scores.shape[1] - 1)
        xs = np.minimum((xs * scale[1]).astype(np.int64), s * scores.shape[2] - 1)
    sub = scores.reshape(-1, s * s, *scores.shape[1:])
    return sub[:, (ys % s) * s + xs % s, ys // s, xs // s]


def upsampled_at(scores: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """(C, N): (C, h, w) scores upsampled 2x bilinearly, at full-resolution pixels (ys, xs),
    as cv2.resize(INTER_LINEAR) to (2w, 2h) computes them (half-pixel centres, edges
    replicated): pixel y sits at y / 2 - 0.25 in the coarse grid, between coarse rows
    (y - 1) // 2 and the next, 3/4 of the way to the next for even y, 1/4 for odd y."""
    c, h, w = scores.shape
    ys, xs = np.asarray(ys, np.int64), np.asarray(xs, np.int64)
    wy = np.where(ys & 1, np.float32(0.25), np.float32(0.75))
    wx = np.where(xs & 1, np.float32(0.25), np.float32(0.75))
    r0, k0 = (ys - 1) >> 1, (xs - 1) >> 1  # floor division, -1 at the first row and column
    r1, k1 = np.minimum(r0 + 1, h - 1) * w, np.minimum(k0 + 1, w - 1)
    r0, k0 = np.maximum(r0, 0) * w, np.maximum(k0, 0)
    flat = scores.reshape(c, -1)
    top = np.take(flat, r0 + k0, axis=1) * (1 - wx) + np.take(flat, r0 + k1, axis=1) * wx
    bottom = np.take(flat, r1 + k0, axis=1) * (1 - wx) + np.take(flat, r1 + k1, axis=1) * wx
    return top * (1 - wy) + bottom * wy


def upsampled_argmax(scores: np.ndarray) -> np.ndarray:
    """argmax_channels(scores upsampled 2x bilinearly) -> (2h, 2w) uint8 labels
    (UpsampledScores(scores).labels)."""
    return UpsampledScores(scores).labels


class UpsampledScores:
    """(C, h, w) scores upsampled 2x bilinearly (as cv2.resize INTER_LINEAR to (2w, 2h)),
    without upsampling the score planes. `labels`: their argmax, (2h, 2w) uint8; calling it
    with pixels (ys, xs) gives their (C, N) upsampled scores (upsampled_at). With `first_row`,
    the blocks wholly above it (rows a caller does not use) are not decided: their pixels
    take the class of the block's first coarse pixel (up and left of them). 41 % of the mixed
    blocks of benchmark frames lie in the context rows above the IPM ROI (2026-12-02).

    A full-resolution pixel blends the 2x2 coarse pixels around it with weights >= 0, so where
    those four share their winning class, the blend's winner is that class too. Only the four
    pixels of each 'mixed' 2x2 block (about 1 in 10 on road frames) are blended and decided;
    the rest copy their block's class. The blends are kept: a paint border runs through mixed
    blocks (88 % of its pixels lie in one), so the scores BorderNet reads there are a lookup.
    Same labels as the resize then argmax (but for exact ties of blended scores); each mixed
    block's four corners are gathered once for its four pixels. Logits of 200 benchmark road
    frames (640x312), thread CPU time p50 / p95: 0.88 / 1.15 ms, against 1.32 / 1.88 blending
    each pixel alone (before 2026-11-25 night) and 1.26 / 1.61 resizing every plane then the
    argmax."""

    def __init__(self, scores: np.ndarray, first_row: int = 0):
        c, h, w = scores.shape
        self.scores = scores
        coarse = argmax_channels(scores)
        padded = cv2.copyMakeBorder(coarse, 1, 1, 1, 1, cv2.BORDER_REPLICATE)
        # block (i, j): coarse pixels (i - 1 .. i, j - 1 .. j), edges replicated; it holds the
        # full-resolution pixels (2i - 1 .. 2i, 2j - 1 .. 2j)
        corner = padded[:-1, :-1]
        mixed = ((corner != padded[1:, :-1]) | (corner != padded[:-1, 1:])
                 | (corner != padded[1:, 1:]))
        mixed[:(first_row + 1) >> 1] = False  # the blocks wholly above first_row: undecided
        labels = cv2.resize(corner, (2 * w + 2, 2 * h + 2), interpolation=cv2.INTER_NEAREST)
        blocks = np.flatnonzero(mixed)
        self._mixed = len(blocks)
        self._block = np.full(mixed.shape, -1, np.int32)  # a mixed block's column in _blend
        self._blend = np.zeros((c, 0), np.float32)
        if len(blocks):
            self._block.reshape(-1)[blocks] = np.arange(len(blocks), dtype=np.int32)
            bi, bj = np.divmod(blocks, w + 1)
            # the block's corners in the score planes, edges replicated by clipping
            top, bottom = np.maximum(bi - 1, 0) * w, np.minimum(bi, h - 1) * w
            left, right = np.maximum(bj - 1, 0), np.minimum(bj, w - 1)
            flat = scores.reshape(c, -1)
            tl, tr = np.take(flat, top + left, axis=1), np.take(flat, top + right, axis=1)
            bl, br = np.take(flat, bottom + left, axis=1), np.take(flat, bottom + right, axis=1)
            # (C, 2 dy + dx, block): a pixel weighs its own corner 3/4 along each axis
            blend = np.empty((c, 4, len(blocks)), np.float32)
            for dx, (near, far) in enumerate(((0.75, 0.25), (0.25, 0.75))):
                upper, lower = tl * near + tr * far, bl * near + br * far
                blend[:, dx] = upper * 0.75 + lower * 0.25
                blend[:, 2 + dx] = upper * 0.25 + lower * 0.75
            self._blend = blend.reshape(c, -1)
            decided = argmax_channels(self._blend).reshape(2, 2, -1)
            pixels = labels.reshape(h + 1, 2, w + 1, 2)  # [i, dy, j, dx]
            for dy in (0, 1):
                for dx in (0, 1):
                    pixels[bi, dy, bj, dx] = decided[dy, dx]
        self.labels = labels[1:-1, 1:-1]

    def __call__(self, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        ys, xs = np.asarray(ys, np.int64), np.asarray(xs, np.int64)
        block = self._block[(ys + 1) >> 1, (xs + 1) >> 1]
        column = block + (((ys + 1) & 1) * 2 + ((xs + 1) & 1)) * self._mixed
        kept = block >= 0
        if kept.all():
            return np.take(self._blend, column, axis=1)
        out = np.empty((len(self.scores), len(ys)), np.float32)
        out[:, kept] = np.take(self._blend, column[kept], axis=1)
        out[:, ~kept] = upsampled_at(self.scores, ys[~kept], xs[~kept])
        return out


def mirror_columns(x: np.ndarray) -> np.ndarray:
    """A float32 (..., h, w) array with its columns reversed, contiguous: OpenCV's flip of the
    (rows, w) view, 3x faster than copying numpy's reversed view (0.07 against 0.22 ms for a
    640x312 input)."""
    flat = np.ascontiguousarray(x).reshape(-1, x.shape[-1])
    return cv2.flip(flat, 1).reshape(x.shape)


def mirrored_back(logits: np.ndarray, s: int = 1) -> np.ndarray:
    """mirror_logits as a contiguous array (plain float32 logits by OpenCV's flip)."""
    if s == 1 and logits.dtype == np.float32 and logits.ndim >= 2:
        return mirror_columns(logits)
    return np.ascontiguousarray(mirror_logits(logits, s))


def mean_with_mirrored(logits: np.ndarray, mirrored: np.ndarray, s: int = 1) -> np.ndarray:
    """The mean of the logits of an image and those of its mirror image (mirror_logits):
    flip averaging. For plain float32 logits by OpenCV (0.09 against 0.22 ms at 6 x 156 x 320,
    the same values: halving is exact)."""
    if s != 1 or logits.dtype != np.float32 or logits.ndim < 2:
        return 0.5 * (logits + mirror_logits(mirrored, s))
    w = logits.shape[-1]
    a = np.ascontiguousarray(logits).reshape(-1, w)
    b = mirror_columns(mirrored).reshape(-1, w)
    return cv2.addWeighted(a, 0.5, b, 0.5, 0.0).reshape(logits.shape)


def mirror_logits(logits: np.ndarray, s: int = 1) -> np.ndarray:
    """Logits (..., C * s * s, h, w) of a mirrored image -> those of the image: columns
    reversed and, for sub-pixel logits (channel c * s * s + s * i + j is class c at pixel
    (s y + i, s x + j)), each sub-pixel column j swapped with s - 1 - j, since full-resolution
    column s x + j of the mirror is column s (w - 1 - x) + (s - 1 - j) of the image."""
    flipped = logits[..., ::-1]
    if s == 1:
        return flipped
    *lead, c, h, w = flipped.shape
    return flipped.reshape(*lead, c // (s * s), s, s, h, w)[..., ::-1, :, :].reshape(
        *lead, c, h, w)


def subpixel_argmax(scores: np.ndarray, s: int) -> np.ndarray:
    """(C * s * s, h, w) sub-pixel logits -> (s h, s w) labels: the argmax of each of the s * s
    sub-grids at (h, w), interleaved (what F.pixel_shuffle then an argmax gives, without moving
    the float planes)."""
    _, h, w = scores.shape
    sub = scores.reshape(-1, s * s, h, w)
    labels = np.empty((s * h, s * w), np.uint8)
    for k in range(s * s):
        labels[k // s::s, k % s::s] = argmax_channels(sub[:, k])  # planes stay contiguous
    return labels


def resize_channels(scores: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(C, h, w) float32 -> (C, H, W) for size (W, H), bilinear, channel by channel into one
    contiguous buffer (an interleaved (H, W, C) resize leaves a strided array that made the
    argmax after it 1.7x slower)."""
    out = np.empty((len(scores), size[1], size[0]), np.float32)
    for c, channel in enumerate(scores):
        cv2.resize(np.ascontiguousarray(channel, np.float32), size, dst=out[c],
                   interpolation=cv2.INTER_LINEAR)
    return out


def argmax_channels(scores: np.ndarray) -> np.ndarray:
    """np.argmax(scores, axis=0) for a few channels (first maximum wins, like np.argmax): the
    running maximum, then each channel from the last to the first claims the pixels where it
    equals the maximum; all in place, about 4x faster than numpy's strided axis-0 argmax on a
    6x360x640 array (NaN scores are not supported)."""
    best = scores[0].copy()
    for c in range(1, len(scores)):
        np.maximum(best, scores[c], out=best)
    arg = np.full(best.shape, len(scores) - 1, np.uint8 if len(scores) < 256 else np.int64)
    hit = np.empty(best.shape, bool)
    for c in range(len(scores) - 2, -1, -1):
        np.equal(scores[c], best, out=hit)
        np.copyto(arg, arg.dtype.type(c), where=hit)
    return arg
