"""F_cnn: the paper's U-Net on the polar BEV, and the learnable softmax of the yaw head.

Encoder-decoder with skip connections: four double-conv blocks with three 2x max-pools
(total stride 8: 40 x 120 -> 5 x 15), bilinear upsampling back, concatenation with the
encoder features, and a 1 x 1 convolution to one output channel at the input's ring x
sector resolution. Input channels are the BEV heights.

Padding is circular along sectors and zero along rings, and upsampling is done on a
circularly padded copy, so the whole network commutes with a roll of the input by any
multiple of 8 sectors: a rotated scan gives an exactly rolled feature image across the
0/360 seam, and the signature |FFT2| is then exactly unchanged.

With `residual=True` (this project's default) the output is the BEV summed over heights
(the training-free `spectral` model) plus the U-Net's output, whose last convolution
starts at zero: training starts from the floor and only has to learn a correction, which
matters when the training budget is minutes on a CPU.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class PolarConv(nn.Module):
    """3 x 3 convolution, circular along sectors (last axis), zero-padded along rings."""

    def __init__(self, cin: int, cout: int, circular: bool = True):
        super().__init__()
        self.circular = circular
        self.conv = nn.Conv2d(cin, cout, 3, padding=0 if circular else 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.circular:
            x = F.pad(x, (1, 1, 0, 0), mode="circular")
            x = F.pad(x, (0, 0, 1, 1))
        return self.conv(x)


def double_conv(cin: int, cout: int, norm: bool, circular: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in ((cin, cout), (cout, cout)):
        layers.append(PolarConv(a, b, circular))
        if norm:
            layers.append(nn.BatchNorm2d(b))
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


def upsample2(x: torch.Tensor, circular: bool = True, align_corners: bool = False) -> torch.Tensor:
    """Bilinear 2x upsampling that wraps around the sector seam instead of clamping."""
    if not circular:
        return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=align_corners)
    x = F.pad(x, (1, 1, 0, 0), mode="circular")
    x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
    return x[..., 2:-2]


class UNet(nn.Module):
    """The U-Net F_cnn: [B, heights, R, S] -> [B, R, S] (R and S multiples of 8)."""

    STRIDE = 8

    def __init__(
        self,
        in_channels: int,
        width: int = 16,
        norm: bool = True,
        circular: bool = True,
        sigmoid: bool = False,
        residual: bool = False,
    ):
        super().__init__()
        w = width
        self.residual = residual
        self.circular = circular
        self.sigmoid = sigmoid
        self.dconv_down1 = double_conv(in_channels, w, norm, circular)
        self.dconv_down2 = double_conv(w, 2 * w, norm, circular)
        self.dconv_down3 = double_conv(2 * w, 4 * w, norm, circular)
        self.dconv_down4 = double_conv(4 * w, 8 * w, norm, circular)
        self.dconv_up3 = double_conv(8 * w + 4 * w, 4 * w, norm, circular)
        self.dconv_up2 = double_conv(4 * w + 2 * w, 2 * w, norm, circular)
        self.dconv_up1 = double_conv(2 * w + w, w, norm, circular)
        self.conv_last = nn.Conv2d(w, 1, 1)
        if residual:
            nn.init.zeros_(self.conv_last.weight)
            nn.init.zeros_(self.conv_last.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.correction(x)
        if self.residual:
            out = out + x.sum(dim=1)
        return out

    def correction(self, x: torch.Tensor) -> torch.Tensor:
        """The convolutional part [B, R, S]: the whole output unless `residual`."""
        c1 = self.dconv_down1(x)
        c2 = self.dconv_down2(F.max_pool2d(c1, 2))
        c3 = self.dconv_down3(F.max_pool2d(c2, 2))
        x = self.dconv_down4(F.max_pool2d(c3, 2))
        # The authors' U-Net upsamples with align_corners=True (no circular wrap).
        ac = not self.circular
        x = self.dconv_up3(torch.cat([upsample2(x, self.circular, ac), c3], dim=1))
        x = self.dconv_up2(torch.cat([upsample2(x, self.circular, ac), c2], dim=1))
        x = self.dconv_up1(torch.cat([upsample2(x, self.circular, ac), c1], dim=1))
        x = self.conv_last(x)
        if self.sigmoid:
            x = torch.sigmoid(x)
        return x[:, 0]


class Corr2Soft(nn.Module):
    """The paper's softmax over the correlation curve: p = softmax(W * curve + b)."""

    def __init__(self, w: float = 20.0, b: float = 0.0):
        super().__init__()
        self.softmax_w = nn.Parameter(torch.tensor([float(w)]))
        self.softmax_b = nn.Parameter(torch.tensor([float(b)]))

    def forward(self, curves: torch.Tensor) -> torch.Tensor:
        """Log-probabilities [B, S] of the sector shift."""
        return F.log_softmax(self.softmax_w * curves + self.softmax_b, dim=-1)


class DiscoNet(nn.Module):
    """F_cnn plus the yaw softmax: the trainable parameters of a DiSCO model."""

    def __init__(
        self,
        in_channels: int,
        width: int = 16,
        norm: bool = True,
        circular: bool = True,
        sigmoid: bool = False,
        residual: bool = False,
    ):
        super().__init__()
        self.unet = UNet(in_channels, width, norm, circular, sigmoid, residual)
        self.corr2soft = Corr2Soft()

    def forward(self, bevs: torch.Tensor) -> torch.Tensor:
        return self.unet(bevs)
