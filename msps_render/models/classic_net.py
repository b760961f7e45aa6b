"""The classic (any-number-of-lights) network: PS-FCN's design (Chen et al., ECCV 2018), CPU-sized.

Why this design: photometric stereo with N calibrated lights needs a network that takes any number
of images in any order.  PS-FCN does it with a feature extractor shared by every image (fed the
image and its light direction), a max-pool across the lights (order-agnostic, any N, and the max
keeps each pixel's most telling observation -- the brightest, unshadowed ones), and a normal
regressor on the pooled features.  It also runs on three lights, which the seed paper's comparison
needs (the three channels of one multispectral image read as three images); an observation-map
network (CNN-PS) needs tens of lights per pixel.  The max-pool is taken as a running maximum over
chunks of lights, so a 96-light DiLiGenT object at full resolution needs the memory of one chunk.

Input convention (`prepare`): each image is divided by its light's reading per channel (so every
image is the one under a unit white light, as DiLiGenT's images divided by their intensities), then
the whole sample by its mean over the object: the network never sees the exposure.  With
`normalize="pixel"` each pixel's observations are then divided by their root mean square over the
lights and channels (PS-FCN (Norm.)'s observation normalisation, Chen et al. TPAMI 2020): a Lambertian
pixel's values no longer depend on its albedo's brightness, so an albedo edge inside a patch is not a
shading edge; the root mean square rather than the norm keeps the values independent of N.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
import torch.nn.functional as F


@dataclass(frozen=True)
class ClassicNetConfig:
    channels: int = 3  # camera channels per image (the rig's M)
    widths: tuple[int, int, int] = (32, 64, 128)  # extractor widths at full, 1/2 and 1/4 resolution
    normalize: str = "object"  # input normalisation (`prepare`): "object" or "pixel"


def _conv(i: int, o: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(i, o, 3, stride, 1), nn.LeakyReLU(0.1, inplace=True))


def _up(i: int, o: int) -> nn.Sequential:
    return nn.Sequential(nn.ConvTranspose2d(i, o, 4, 2, 1), nn.LeakyReLU(0.1, inplace=True))


class ClassicNet(nn.Module):
    """PS-FCN-style: shared extractor per (image, light) -> max over lights -> normal regressor."""

    def __init__(self, cfg: ClassicNetConfig = ClassicNetConfig()):
        super().__init__()
        self.cfg = cfg
        a, b, c = cfg.widths
        self.extract = nn.Sequential(_conv(cfg.channels + 3, a), _conv(a, b, 2), _conv(b, b), _conv(b, c, 2),
                                     _conv(c, c), _up(c, b), _conv(b, b))
        self.regress = nn.Sequential(_conv(b, b), _conv(b, b), _up(b, a), nn.Conv2d(a, 3, 3, 1, 1))

    def features(self, images: torch.Tensor, dirs: torch.Tensor, chunk: int = 0) -> torch.Tensor:
        """Max over lights of the extractor's features: images (B, K, C, H, W), dirs (B, K, 3)."""
        B, K, C, H, W = images.shape
        step = chunk or K
        pooled = None
        for k0 in range(0, K, step):
            im = images[:, k0:k0 + step]
            d = dirs[:, k0:k0 + step, :, None, None].expand(-1, -1, -1, H, W)
            k = im.shape[1]
            f = self.extract(torch.cat([im, d.to(im.dtype)], 2).reshape(B * k, C + 3, H, W))
            f = f.reshape(B, k, *f.shape[1:]).amax(1)
            pooled = f if pooled is None else torch.maximum(pooled, f)
        return pooled

    def forward(self, images: torch.Tensor, dirs: torch.Tensor, chunk: int = 0) -> torch.Tensor:
        """Unit normals (B, 3, H, W); H and W must be multiples of 4 (`pad4`)."""
        return F.normalize(self.regress(self.features(images, dirs, chunk)), dim=1)


PIXEL_FLOOR = 0.01  # `prepare(normalize="pixel")`: darker pixels (in units of the object's mean) keep their scale


def prepare(images: torch.Tensor, readings: torch.Tensor, mask: torch.Tensor, normalize: str = "object") -> torch.Tensor:
    """images (B, K, C, H, W) / their lights' readings (B, K, C), then / the sample's mean over the object;
    `normalize="pixel"`: then each object pixel / its observations' root mean square over lights and
    channels (off the object 0; a pixel darker than `PIXEL_FLOOR` of the object's mean is not lifted)."""
    x = images / readings.clamp_min(1e-8)[..., None, None]
    m = mask[:, None, None].to(x.dtype)  # (B, 1, 1, H, W)
    mean = (x * m).sum((1, 2, 3, 4)) / (m.sum((1, 2, 3, 4)) * x.shape[1] * x.shape[2]).clamp_min(1.0)
    x = x / mean.clamp_min(1e-8)[:, None, None, None, None]
    if normalize == "object":
        return x
    if normalize != "pixel":
        raise ValueError(f"normalize must be 'object' or 'pixel', not {normalize!r}")
    rms = (x * x).mean((1, 2), keepdim=True).sqrt()
    return x * m / rms.clamp_min(PIXEL_FLOOR)


def pad4(x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
    """Pad the last two dims up to multiples of 4 (the extractor halves twice); returns the pads."""
    H, W = x.shape[-2:]
    ph, pw = (-H) % 4, (-W) % 4
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph))
    return x, (ph, pw)


def cosine_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean (1 - cos) over object pixels: pred, gt (B, 3, H, W), mask (B, H, W)."""
    m = mask.to(pred.dtype)
    return ((1 - (pred * gt).sum(1)) * m).sum() / m.sum().clamp_min(1.0)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
