"""RoadSegNet: a compact encoder-decoder for our 6 classes (torch; imported only for training).

Runs on the camera's full resolution (640x360): a 4x4 stride-2 stem sees every pixel (thin,
far paint is 1-3 px wide there and would vanish in a downscaled input), depthwise-separable
blocks at 1/4, 1/8 and 1/16 with dilated context, U-Net skips back to 1/2, and the class logits
upsampled bilinearly to the input size (sub-pixel class boundaries at a 1/2-resolution cost):
in training here, by the runtime after export (OnnxSegmenter; the exported graph ends at 1/2
resolution, since onnxruntime's Resize took 2 of 12 ms and OpenCV's the same upsampling 0.6).
Input (N, 3, H, W) float in [0, 1]; output logits (N, num_classes, H, W). Trained with auxiliary
classes beyond ours (raised curbs), it folds them into none for export: with `export_classes`
set, channel 0 becomes the maximum of none and the auxiliary channels (so argmax picks none
wherever an auxiliary class wins), at 1/2 resolution before the upsampling."""

import torch
from torch import nn
from torch.nn import functional as F

from common.classes import NUM_CLASSES


class ConvBN(nn.Sequential):
    def __init__(self, c_in, c_out, k=3, stride=1, dilation=1, groups=1, act=True):
        pad = dilation * (k // 2)
        layers = [nn.Conv2d(c_in, c_out, k, stride, pad, dilation=dilation, groups=groups,
                            bias=False), nn.BatchNorm2d(c_out)]
        if act:
            layers.append(nn.ReLU(inplace=True))
        super().__init__(*layers)


class DSBlock(nn.Module):
    """Depthwise 3x3 (optionally strided or dilated) + pointwise 1x1; residual when shapes match."""

    def __init__(self, c_in, c_out, stride=1, dilation=1):
        super().__init__()
        self.dw = ConvBN(c_in, c_in, 3, stride, dilation, groups=c_in)
        self.pw = ConvBN(c_in, c_out, 1, act=False)
        self.residual = stride == 1 and c_in == c_out

    def forward(self, x):
        y = self.pw(self.dw(x))
        return F.relu(y + x if self.residual else y)


class RoadSegNet(nn.Module):
    """widths: channels at 1/2, 1/4, 1/8, 1/16; depths: residual blocks at 1/4, at 1/8, and
    dilated context blocks at 1/16 (dilations 2, 4, 8, 2, ...); rows: a learned embedding of the
    pixel row (r, r^2 of the row's place in the full frame, -1 top .. 1 bottom) added at 1/8 and
    1/16. The row tells how far away the ground is: a 0.12 m lane line crossing the view at 8 m
    and a 0.3 m stop line at 20 m are the same few pixels high, and a convolution alone cannot
    tell where in the frame it looks (training crops hide it further). The cost is 1/8 and 1/16
    resolution work only (the 1/2 stage, which dominates the time, is unchanged)."""

    def __init__(self, widths=(16, 24, 32, 48), num_classes=NUM_CLASSES, depths=(1, 1, 2),
                 rows=False, subpixel=1):
        super().__init__()
        w0, w1, w2, w3 = widths
        d1, d2, d3 = depths
        self.arch = {"widths": list(widths), "depths": list(depths), "rows": bool(rows)}
        # subpixel s > 1: the head gives s x s logits per class at 1/2 resolution (channel
        # c * s * s + i * s + j: class c at pixel (s y + i, s x + j), as F.pixel_shuffle lays
        # them out): full-resolution logits without a full-resolution stage
        self.subpixel = int(subpixel)
        if self.subpixel > 1:
            self.arch["subpixel"] = self.subpixel
        self.stem = nn.Sequential(nn.Conv2d(3, w0, 4, 2, 1, bias=False), nn.BatchNorm2d(w0),
                                  nn.ReLU(inplace=True))  # 1/2, from every input pixel
        self.down1 = DSBlock(w0, w1, stride=2)  # 1/4
        self.enc1 = nn.Sequential(*[DSBlock(w1, w1) for _ in range(d1)])
        self.down2 = DSBlock(w1, w2, stride=2)  # 1/8
        self.enc2 = nn.Sequential(*[DSBlock(w2, w2) for _ in range(d2)])
        self.down3 = DSBlock(w2, w3, stride=2)  # 1/16
        self.context = nn.Sequential(*[DSBlock(w3, w3, dilation=(2, 4, 8)[i % 3])
                                       for i in range(d3)])
        self.rows2 = nn.Conv2d(2, w2, 1, bias=False) if rows else None
        self.rows3 = nn.Conv2d(2, w3, 1, bias=False) if rows else None
        self.dec2 = DSBlock(w3 + w2, w2)
        self.dec1 = DSBlock(w2 + w1, w1)
        self.dec0 = DSBlock(w1 + w0, w0)
        self.head = nn.Conv2d(w0, num_classes * self.subpixel ** 2, 1)
        self.export_classes = None  # set to NUM_CLASSES to fold the auxiliary classes into 0
        self.crop_rows = None  # (row0, frame height) while training on crops
        # export: logits at 1/2 resolution; the runtime upsamples them (OnnxSegmenter)
        self.half_res_logits = False

    def forward(self, x):
        """x: (N, 3, H, W). For a crop of a frame, set `crop_rows` = (row of the crop's top in
        the frame, the frame's height) first, so the row embedding sees where its rows are."""
        row0, full_h = self.crop_rows or (0, x.shape[-2])
        f0 = self.stem(x)
        f1 = self.enc1(self.down1(f0))
        f2 = self.down2(f1)
        if self.rows2 is not None:
            f2 = f2 + self.rows2(_row_features(f2, 8, row0, full_h))
        f2 = self.enc2(f2)
        f3 = self.down3(f2)
        if self.rows3 is not None:
            f3 = f3 + self.rows3(_row_features(f3, 16, row0, full_h))
        f3 = self.context(f3)
        d2 = self.dec2(torch.cat([upsample_like(f3, f2), f2], 1))
        d1 = self.dec1(torch.cat([upsample_like(d2, f1), f1], 1))
        d0 = self.dec0(torch.cat([upsample_like(d1, f0), f0], 1))
        logits = self.head(d0)
        s2 = self.subpixel ** 2
        if s2 > 1:  # (N, C * s2, h, w) -> (N, C, s2, h, w): folded per sub-pixel below
            logits = logits.unflatten(1, (-1, s2))
        n = self.export_classes
        if n is not None and n < logits.shape[1]:
            extra = logits[:, n:]  # one auxiliary class (curbs): no reduction over it in
            # the graph (an ONNX ReduceMax over one channel cost 0.4 ms of a 7.6 ms pass)
            extra = extra if extra.shape[1] == 1 else extra.amax(1, keepdim=True)
            none = torch.maximum(logits[:, :1], extra)
            logits = torch.cat([none, logits[:, 1:n]], 1)
        if s2 > 1:
            logits = logits.flatten(1, 2)
            return logits if self.half_res_logits else F.pixel_shuffle(logits, self.subpixel)
        return logits if self.half_res_logits else upsample_like(logits, x)


def _row_features(f, stride: int, row0: int, full_h: int):
    """(1, 2, h, 1): r and r^2 of each feature row's centre in the full frame (r in [-1, 1])."""
    centre = row0 + (torch.arange(f.shape[-2], device=f.device, dtype=f.dtype) + 0.5) * stride
    r = (2.0 * centre / full_h - 1.0).view(1, 1, -1, 1)
    return torch.cat([r, r * r], 1)


def upsample_like(x, like):
    """x resized bilinearly (half-pixel centres) to the height and width of `like`."""
    return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def load_onnx_weights(model: nn.Module, path) -> None:
    """Initialise `model` from an exported RoadSegNet ONNX file of the same widths (for
    fine-tuning). The export folded each batch norm into its convolution, so the convolutions
    take the folded weights and every batch norm becomes the identity with the folded bias as
    its shift (running mean 0, variance 1 - eps); keep batch norms in eval mode while
    fine-tuning (`freeze_batch_norm`). Convolutions are matched in execution order; a head with
    more classes than the file's keeps the file's rows and starts the extra ones as copies of
    row 0 (none), so the auxiliary classes begin as 'none' and split off from it; a sub-pixel
    head from a 1/2-resolution one starts each sub-pixel as a copy of its pixel (the file's
    model with nearest-neighbour upsampling). Decoder blocks split for speed
    (onnx_graph.split_concatenations) are merged back."""
    import onnx
    from onnx import numpy_helper

    from training.onnx_graph import merged_convolutions

    proto = onnx.load(str(path))
    tensors = {t.name: numpy_helper.to_array(t) for t in proto.graph.initializer}
    for node in proto.graph.node:  # the exporter shares equal initializers via Identity
        if node.op_type == "Identity" and node.input[0] in tensors:
            tensors[node.output[0]] = tensors[node.input[0]]
    nodes = merged_convolutions(proto, tensors)
    convs: list[nn.Conv2d] = []
    hooks = [m.register_forward_hook(lambda m, i, o: convs.append(m))
             for m in model.modules() if isinstance(m, nn.Conv2d)]
    was_training = model.training
    model.eval()
    with torch.no_grad():
        model(torch.zeros(1, 3, 64, 64))
    model.train(was_training)
    for h in hooks:
        h.remove()
    if len(nodes) != len(convs):
        raise ValueError(f"{path}: {len(nodes)} convolutions, the model has {len(convs)}")
    norm_after = {}
    for seq in model.modules():
        if isinstance(seq, nn.Sequential):
            for a, b in zip(seq, list(seq)[1:], strict=False):
                if isinstance(a, nn.Conv2d) and isinstance(b, nn.BatchNorm2d):
                    norm_after[a] = b
    s2 = getattr(model, "subpixel", 1) ** 2
    with torch.no_grad():
        for (name, weight, bias), conv in zip(nodes, convs, strict=True):
            w = torch.from_numpy(weight.copy())
            b = torch.from_numpy(bias.copy()) if bias is not None else torch.zeros(w.shape[0])
            if conv is convs[-1] and w.shape[0] * s2 <= conv.weight.shape[0]:  # the head
                extra = conv.weight.shape[0] // s2 - w.shape[0]
                if extra > 0:  # auxiliary classes start as none
                    w = torch.cat([w, w[:1].repeat(extra, 1, 1, 1)])
                    b = torch.cat([b, b[:1].repeat(extra)])
                if s2 > 1:  # from a 1/2-resolution head: each sub-pixel starts as its pixel
                    w, b = w.repeat_interleave(s2, 0), b.repeat_interleave(s2, 0)
            if w.shape != conv.weight.shape:
                raise ValueError(f"{path}: {name} has weights {tuple(w.shape)}, "
                                 f"the model {tuple(conv.weight.shape)}")
            conv.weight.copy_(w)
            norm = norm_after.get(conv)
            if norm is None:
                conv.bias.copy_(b)
                continue
            norm.weight.fill_(1.0)
            norm.bias.copy_(b)
            norm.running_mean.zero_()
            norm.running_var.fill_(1.0 - norm.eps)


def onnx_widths(path) -> list[int]:
    """The widths (channels at 1/2, 1/4, 1/8, 1/16) of an exported RoadSegNet: the stem's
    outputs, then the outputs of each strided block's pointwise convolution (the first 1x1
    convolution after each stride-2 depthwise one)."""
    import onnx

    proto = onnx.load(str(path))
    shapes = {t.name: t.dims for t in proto.graph.initializer}
    convs = [n for n in proto.graph.node if n.op_type == "Conv"]
    strides = [next((list(a.ints) for a in n.attribute if a.name == "strides"), [1, 1])
               for n in convs]
    widths = [int(shapes[convs[0].input[1]][0])]
    for i in range(1, len(convs) - 1):
        if strides[i] == [2, 2]:
            widths.append(int(shapes[convs[i + 1].input[1]][0]))
    if len(widths) != 4:
        raise ValueError(f"{path}: not a RoadSegNet export (strided stages {len(widths)})")
    return widths


def widen(small: nn.Module, wide: nn.Module) -> None:
    """Copy a trained RoadSegNet into one with more channels per stage (same depths and head),
    so that `wide` computes exactly what `small` does: every old channel keeps its weights, each
    new channel starts from `wide`'s own initialisation, and the weights from new channels
    into old ones (and into the head) start at zero, so the new channels are ignored until
    training finds a use for them. New batch norms are the identity (as `load_onnx_weights`
    leaves the folded ones). Why: onnxruntime's blocked convolutions pad channels to 16 on
    AVX-512, so widths [16, 32, 48, 64] cost no more than [12, 20, 40, 64] (archs.py); the
    wider model can be fine-tuned from the narrower one instead of from scratch."""
    modules, old = dict(wide.named_modules()), dict(small.named_modules())
    with torch.no_grad():
        for name, conv, src, out_map, in_map in _channel_maps(small, wide):
            w = conv.weight
            if conv.groups > 1:
                w[out_map] = src.weight
            else:
                w[out_map] = 0.0
                w[out_map[:, None], in_map[None, :]] = src.weight
            if conv.bias is not None:
                conv.bias[out_map] = src.bias
            norm, src_norm = _norm_after(modules, name), _norm_after(old, name)
            if norm is not None:
                norm.weight.fill_(1.0)
                norm.bias.zero_()
                norm.running_mean.zero_()
                norm.running_var.fill_(1.0 - norm.eps)
                for key in ("weight", "bias", "running_mean", "running_var"):
                    getattr(norm, key)[out_map] = getattr(src_norm, key)


def narrow(wide: nn.Module, small: nn.Module) -> None:
    """The inverse of `widen`: copy the channels of `wide` that `small` has into `small`.
    `small` computes what `wide` does when the dropped channels are never read (an `aligned`
    export, whose padding channels are zeros); the caller checks that."""
    modules, big = dict(small.named_modules()), dict(wide.named_modules())
    for name, src, conv, out_map, in_map in _channel_maps(small, wide):
        gather_channels(conv, src, out_map, in_map, _norm_after(modules, name),
                        _norm_after(big, name))


def gather_channels(conv: nn.Conv2d, src: nn.Conv2d, out_map, in_map, norm=None,
                    src_norm=None) -> None:
    """Set `conv` (and its batch norm `norm`, if any) to the output channels `out_map` of
    `src` (and of `src_norm`), reading its input channels `in_map` (a depthwise convolution's
    one input channel is its output's)."""
    with torch.no_grad():
        conv.weight.copy_(src.weight[out_map] if conv.groups > 1
                          else src.weight[out_map[:, None], in_map[None, :]])
        if conv.bias is not None:
            conv.bias.copy_(src.bias[out_map])
        if norm is not None:
            for key in ("weight", "bias", "running_mean", "running_var"):
                getattr(norm, key).copy_(getattr(src_norm, key)[out_map])


def aligned(model: nn.Module, block: int = 16) -> nn.Module:
    """`model` (eval mode) with every stage's channels rounded up to a multiple of `block`,
    the new ones zeros (`widen` from an all-zero model): the same function, which onnxruntime
    runs faster. Its blocked (NCHWc) convolutions pad channels to 16 on AVX-512 anyway, but
    a 12-, 20- or 40-channel tensor must leave that layout to be concatenated with a skip or
    read by a pointwise convolution: at [12, 20, 40, 64], 7 reorders and 3 concatenations
    between the two layouts took 1.1 ms of the 9.5 ms network (one thread, 640x312,
    2026-11-25); [16, 32, 48, 64] keeps the blocked layout but for the 1/16 -> 1/8 resize."""
    widths = [-(-w // block) * block for w in model.arch["widths"]]
    if widths == model.arch["widths"]:
        return model
    s2 = model.subpixel ** 2
    wide = RoadSegNet(widths=widths, num_classes=model.head.out_channels // s2,
                      depths=model.arch["depths"], rows=model.arch["rows"],
                      subpixel=model.subpixel)
    with torch.no_grad():
        for p in wide.parameters():
            p.zero_()
    widen(model, wide)
    wide.eval()
    for key in ("export_classes", "crop_rows", "half_res_logits"):
        setattr(wide, key, getattr(model, key))
    return wide


def _channel_maps(small: nn.Module, wide: nn.Module):
    """(name, wide's conv, small's conv, out_map, in_map) for each convolution of two
    RoadSegNets of the same depths, `wide` at least as wide in every stage: the indices in
    wide's output and input channels of small's (a decoder block's depthwise convolution
    outputs, and its pointwise one reads, the concatenation [upsampled deep, skip])."""
    (w0, w1, w2, w3), (_, n1, n2, n3) = small.arch["widths"], wide.arch["widths"]
    if small.arch["depths"] != wide.arch["depths"] or any(
            n < w for n, w in zip(wide.arch["widths"], small.arch["widths"], strict=True)):
        raise ValueError(f"cannot widen {small.arch} into {wide.arch}")

    def concat(deep_old, deep_new, skip_old):  # cat([up(deep), skip]) channel positions
        return torch.cat([torch.arange(deep_old), deep_new + torch.arange(skip_old)])

    # every other channel keeps its index
    cat_in = {"dec2": concat(w3, n3, w2), "dec1": concat(w2, n2, w1), "dec0": concat(w1, n1, w0)}
    old = dict(small.named_modules())
    for name, conv in wide.named_modules():
        if not isinstance(conv, nn.Conv2d):
            continue
        src = old[name]
        block = name.split(".")[0]
        depthwise = conv.groups > 1
        out_map = (cat_in[block] if block in cat_in and depthwise
                   else torch.arange(src.out_channels))
        in_map = (cat_in[block] if block in cat_in and not depthwise
                  else torch.arange(src.in_channels // src.groups))
        yield name, conv, src, out_map, in_map


def _norm_after(modules: dict, conv_name: str):
    """The batch norm after convolution `conv_name` in a ConvBN (its sibling '.1'), or None."""
    if not conv_name.endswith(".0"):
        return None
    norm = modules.get(conv_name.rsplit(".", 1)[0] + ".1")
    return norm if isinstance(norm, nn.BatchNorm2d) else None


def freeze_batch_norm(model: nn.Module) -> None:
    """Batch norms in eval mode (running statistics kept, affine still trained)."""
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.eval()
