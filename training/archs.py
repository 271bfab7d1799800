"""Named RoadSegNet sizes (`roadmap train-seg --arch`), without torch: the CLI offers them as
choices, training/net.py builds them.

Channel counts keep w0 + w1 a multiple of 16 (the 1/2-resolution concatenation; onnxruntime's
blocked convolutions pad to 16 on AVX-512). One onnxruntime thread at 640x360 on this 2-core
machine: s 10.7 ms, m 11.9 ms (network only)."""

ARCHS = {
    "s": {"widths": [12, 20, 40, 64], "depths": [1, 1, 2], "rows": False},  # 26 k parameters
    "m": {"widths": [12, 20, 44, 84], "depths": [1, 2, 4], "rows": True},  # 55 k parameters
}
ARCHS["m-norows"] = {**ARCHS["m"], "rows": False}
# "s" with the channels that the blocked convolutions compute anyway (12 -> 16, 20 -> 32,
# 40 -> 48): 11.66 ms against 11.50 for s (segment_model_size, 150 frames alternated,
# 2026-11-25 afternoon), but the network alone 8.51 against 9.59 ms that night (thread CPU
# time, 400 runs alternated): every export is now padded to these widths (net.aligned).
# Fine-tuned from a narrower export (`--init`), it starts as that model (net.widen).
ARCHS["w16"] = {**ARCHS["s"], "widths": [16, 32, 48, 64]}
# "s" with a sub-pixel head: full-resolution logits from the 1/2 stage, at the same time
ARCHS["s-sub"] = {**ARCHS["s"], "subpixel": 2}
# "s" with its 1/4-resolution channels pruned from 20 to 16 (encoder and decoder: the 1/2
# decoder then reads 16 upsampled channels instead of 32 padded ones) and the rest at the widths
# the blocked convolutions compute anyway: 5.6 against 7.9 ms a pass (one thread, 640x312)
ARCHS["p16"] = {**ARCHS["s"], "widths": [16, 16, 48, 64]}
# A capacity probe, not a product size: 16x "s"'s parameters (410 k), about 3x its 1/2-resolution
# work. It asks whether a larger network learns more from the same towns (stop 47's GPU run).
ARCHS["xl"] = {"widths": [32, 48, 128, 192], "depths": [2, 4, 6], "rows": False}
# Between p16 and xl: xl's extra capacity where it is cheap, at 1/8 and 1/16, on p16's 1/2 and
# 1/4 widths. m64 is the packaged model's (run G2R, common/models/MODEL_CARD.md); d192 was
# trained once (HISTORY.md, 2026-11-28 early morning). One onnxruntime thread at 640x312 on a
# 2-core AVX2 EPYC, exported as the product exports (the least of 40 passes, 2026-11-27): s
# 16.4 ms, m64 15.5 ms (112 k parameters), d192 21.8 ms (364 k), xl 51.3 ms.
ARCHS["m64"] = {"widths": [16, 16, 64, 128], "depths": [1, 2, 4], "rows": False}
ARCHS["d192"] = {"widths": [16, 16, 64, 192], "depths": [1, 2, 8], "rows": False}
