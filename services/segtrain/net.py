"""RoadSegNet: a compact encoder-decoder for our 6 classes (torch; imported only for training).

Runs on the camera's full resolution (640x360): a 4x4 stride-2 stem sees every pixel (thin,
far paint is 1-3 px wide there and would vanish in a downscaled input), depthwise-separable
blocks at 1/4, 1/8 and 1/16 with dilated context, U-Net skips back to 1/2, and the class logits
upsampled bilinearly to the input size (sub-pixel class boundaries at a 1/2-resolution cost).
Input (N, 3, H, W) float in [0, 1]; output logits (N, 6, H, W)."""

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
    def __init__(self, widths=(16, 24, 32, 48), num_classes=NUM_CLASSES):
        super().__init__()
        w0, w1, w2, w3 = widths
        self.stem = nn.Sequential(nn.Conv2d(3, w0, 4, 2, 1, bias=False), nn.BatchNorm2d(w0),
                                  nn.ReLU(inplace=True))  # 1/2, from every input pixel
        self.down1 = DSBlock(w0, w1, stride=2)  # 1/4
        self.enc1 = DSBlock(w1, w1)
        self.down2 = DSBlock(w1, w2, stride=2)  # 1/8
        self.enc2 = DSBlock(w2, w2)
        self.down3 = DSBlock(w2, w3, stride=2)  # 1/16
        self.context = nn.Sequential(DSBlock(w3, w3, dilation=2), DSBlock(w3, w3, dilation=4))
        self.dec2 = DSBlock(w3 + w2, w2)
        self.dec1 = DSBlock(w2 + w1, w1)
        self.dec0 = DSBlock(w1 + w0, w0)
        self.head = nn.Conv2d(w0, num_classes, 1)

    def forward(self, x):
        f0 = self.stem(x)
        f1 = self.enc1(self.down1(f0))
        f2 = self.enc2(self.down2(f1))
        f3 = self.context(self.down3(f2))
        d2 = self.dec2(torch.cat([_up(f3, f2), f2], 1))
        d1 = self.dec1(torch.cat([_up(d2, f1), f1], 1))
        d0 = self.dec0(torch.cat([_up(d1, f0), f0], 1))
        return _up(self.head(d0), x)


def _up(x, like):
    return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
