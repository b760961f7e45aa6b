"""The dual-cue network: n_est = PCN(c, SCN(c))  (Ju et al. 2020; docs/history.md).

SCN (structural cue): the R, G, B channels go through separate conv branches
(spectral-division multiplexing), an Interleaved Group Convolution block mixes
them (primary group conv per channel branch, channel permutation, secondary
group conv whose groups each take one channel from every primary group), then
a U-Net (three stride-2 downs 40->20->10->5, three transposed-conv ups with
skip connections) and 1x1 convs give a coarse normal map.

PCN (photometric cue): a per-pixel multi-branch fully connected net on
[observation (3), coarse normal (3)]: one branch per input, merged, then FC
layers, L2-normalised.  Per-pixel FC layers are written as 1x1 convolutions,
which is the same computation without reshaping to (B*H*W, 6).

Chroma cue (`chroma_cue`, off in every shipped model up to v0.4): each colour
channel divided by its own patch mean is fed next to the observation, to every
SCN branch and to the PCN observation branch.  A uniform albedo colour cancels in
it, so it carries the shape without the colour/light ambiguity; `widen_inputs`
warm-starts such a net from one without it (new weights zero: same output).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F


@dataclass(frozen=True)
class NetConfig:
    branch: int = 8  # features per colour-channel branch
    unet: tuple[int, int, int, int] = (24, 48, 64, 96)  # widths at 40, 20, 10, 5
    pcn_branch: int = 32  # width of each PCN input branch
    pcn: tuple[int, ...] = (64, 64, 32, 32)  # PCN FC widths after the merge
    mode: str = "dual"  # dual | scn | pcn
    chroma_cue: bool = False  # add each channel divided by its own patch mean as a second input
    lambert_cue: bool = False  # give the PCN the calibrated Lambertian normal and its unit-length residual
    lambert_scn: bool = False  # ... and the SCN's U-Net too (beside the colour branches' features)
    cue_gain: float = 1.0  # the Lambertian cue is multiplied by this: its zero-initialised weights learn this much faster

    def __post_init__(self):
        if self.mode not in ("dual", "scn", "pcn"):
            raise ValueError(f"mode must be dual, scn or pcn, got {self.mode!r}")


def _conv(cin: int, cout: int, stride: int = 1, groups: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, groups=groups, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU(inplace=True))


class IGCBlock(nn.Module):
    """Interleaved group convolution (Zhang et al. 2017) over `g1` channel-branch groups."""

    def __init__(self, channels: int, g1: int = 3):
        super().__init__()
        if channels % g1:
            raise ValueError("channels must be divisible by the number of primary groups")
        self.g1, self.g2 = g1, channels // g1
        self.primary = nn.Conv2d(channels, channels, 3, 1, 1, groups=g1, bias=False)
        self.secondary = nn.Conv2d(channels, channels, 1, groups=self.g2, bias=False)
        self.bn = nn.BatchNorm2d(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.primary(x)
        B, C, H, W = y.shape
        # permutation: secondary group j gets channel j of every primary group
        y = y.view(B, self.g1, self.g2, H, W).transpose(1, 2).reshape(B, C, H, W)
        y = self.secondary(y)
        y = y.view(B, self.g2, self.g1, H, W).transpose(1, 2).reshape(B, C, H, W)  # back to branch order
        return F.relu(self.bn(y) + x)


class SCN(nn.Module):
    def __init__(self, cfg: NetConfig):
        super().__init__()
        b = cfg.branch
        self.per_branch = 2 if cfg.chroma_cue else 1  # inputs per colour branch: [x_c] or [x_c, x_c / mean(x_c)]
        self.branches = nn.ModuleList([nn.Sequential(_conv(self.per_branch, b), _conv(b, b)) for _ in range(3)])
        self.igc = IGCBlock(3 * b, 3)
        c0, c1, c2, c3 = cfg.unet
        self.enc0 = _conv(3 * b + (LAMBERT_CHANNELS if cfg.lambert_scn else 0), c0)
        self.down1, self.enc1 = _conv(c0, c1, 2), _conv(c1, c1)
        self.down2, self.enc2 = _conv(c1, c2, 2), _conv(c2, c2)
        self.down3, self.enc3 = _conv(c2, c3, 2), _conv(c3, c3)
        self.up3 = nn.ConvTranspose2d(c3, c2, 4, 2, 1)
        self.dec2 = _conv(2 * c2, c2)
        self.up2 = nn.ConvTranspose2d(c2, c1, 4, 2, 1)
        self.dec1 = _conv(2 * c1, c1)
        self.up1 = nn.ConvTranspose2d(c1, c0, 4, 2, 1)
        self.dec0 = _conv(2 * c0, c0)
        self.head = nn.Sequential(nn.Conv2d(c0, c0, 1), nn.ReLU(inplace=True), nn.Conv2d(c0, 3, 1))

    def forward(self, x: torch.Tensor, lambert: torch.Tensor | None = None) -> torch.Tensor:
        """`x`: (B, 3 * per_branch, H, W), channel-major ([r, g, b] or [r, g, b, r', g', b']);
        `lambert`: the (B, 4, H, W) Lambertian cue, joined to the branches' features (`lambert_scn`)."""
        f = torch.cat([br(x[:, i::3]) for i, br in enumerate(self.branches)], 1)
        f = self.igc(f)
        if lambert is not None:
            f = torch.cat([f, lambert], 1)
        e0 = self.enc0(f)
        e1 = self.enc1(self.down1(e0))
        e2 = self.enc2(self.down2(e1))
        e3 = self.enc3(self.down3(e2))
        d2 = self.dec2(torch.cat([self.up3(e3), e2], 1))
        d1 = self.dec1(torch.cat([self.up2(d2), e1], 1))
        d0 = self.dec0(torch.cat([self.up1(d1), e0], 1))
        return F.normalize(self.head(d0), dim=1)


class PCN(nn.Module):
    """Per-pixel multi-branch FC: observation branch + coarse-normal branch -> merged FC -> unit normal."""

    def __init__(self, cfg: NetConfig, with_normal: bool = True):
        super().__init__()
        w = cfg.pcn_branch
        self.with_normal = with_normal
        n_obs = (6 if cfg.chroma_cue else 3) + (LAMBERT_CHANNELS if cfg.lambert_cue else 0)
        self.obs = nn.Sequential(nn.Conv2d(n_obs, w, 1), nn.ReLU(inplace=True))
        self.nrm = nn.Sequential(nn.Conv2d(3, w, 1), nn.ReLU(inplace=True)) if with_normal else None
        layers, cin = [], w * (2 if with_normal else 1)
        for cout in cfg.pcn:
            layers += [nn.Conv2d(cin, cout, 1), nn.ReLU(inplace=True)]
            cin = cout
        layers.append(nn.Conv2d(cin, 3, 1))
        self.fc = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor, coarse: torch.Tensor | None = None) -> torch.Tensor:
        f = self.obs(obs)
        if self.with_normal:
            f = torch.cat([f, self.nrm(coarse)], 1)
        return F.normalize(self.fc(f), dim=1)


def normalise_observation(x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Divide each patch by its mean object intensity: makes the net exposure-invariant
    (radiance scale depends on light power and albedo, not on shape)."""
    if mask is None:
        mask = (x.sum(1, keepdim=True) > 0).float()
    s = (x * mask).sum((1, 2, 3), keepdim=True) / (3 * mask.sum((1, 2, 3), keepdim=True)).clamp_min(1.0)
    return x / s.clamp_min(1e-6)


def chroma_normalise(x: torch.Tensor, mask: torch.Tensor | None = None, floor: float = 0.02) -> torch.Tensor:
    """Divide each channel by its own mean over the patch's object pixels.

    Why: with a uniform albedo, x_c = rho_c * shading_c, so x_c / mean(x_c) no longer depends
    on rho_c -- a grey and a coloured object with the same shape give the same cue, which is
    exactly the ambiguity a single multiplexed image has.  Applied after
    `normalise_observation`, whose output has mean 1, so `floor` (a channel at 2 % of the
    mean) bounds the gain of a nearly black channel."""
    if mask is None:
        mask = (x.sum(1, keepdim=True) > 0).float()
    m = (x * mask).sum((2, 3), keepdim=True) / mask.sum((2, 3), keepdim=True).clamp_min(1.0)
    return x / m.clamp_min(floor)


LAMBERT_CHANNELS = 4  # Lambertian normal (3) + log of its unnormalised length against the patch's (1)


def lambertian_cue(image: torch.Tensor, mask: torch.Tensor, rig: torch.Tensor) -> torch.Tensor:
    """(B, 4, H, W): calibrated Lambertian PS per pixel, b = (M L)^-1 c, as the unit normal b / |b| and
    log(|b|^2 / mean over the patch).

    Why: on a uniform-albedo Lambertian pixel lit by all three lights b is rho * n exactly, so the
    normal is the answer and the log term is 0; shadows, highlights, interreflections and albedo
    changes show up as a log term away from 0.  The network learns where to trust it -- a fusion
    of the physics and the learned cues (docs/history.md "stage 7")."""
    if rig.ndim == 2:
        rig = rig.expand(image.shape[0], 3, 3)
    b = torch.einsum("bij,bjhw->bihw", torch.linalg.inv(rig.to(image.dtype)), image)
    q = (b * b).sum(1, keepdim=True)
    qm = (q * mask).sum((2, 3), keepdim=True) / mask.sum((2, 3), keepdim=True).clamp_min(1.0)
    n = b / q.sqrt().clamp_min(1e-12)
    logq = torch.log(q.clamp_min(1e-12) / qm.clamp_min(1e-12)).clamp(-3.0, 3.0)
    return torch.cat([n, logq], 1) * mask


class DualCueNet(nn.Module):
    """`forward(image, mask, rig)` -> (final normal, coarse normal or None), both (B, 3, H, W).

    `rig` (B, 3, 3) or (3, 3) = crosstalk @ light_dirs, needed only by a net with `lambert_cue`."""

    def __init__(self, cfg: NetConfig = NetConfig()):
        super().__init__()
        self.cfg = cfg
        self.scn = SCN(cfg) if cfg.mode in ("dual", "scn") else None
        self.pcn = PCN(cfg, with_normal=cfg.mode == "dual") if cfg.mode in ("dual", "pcn") else None

    @property
    def needs_rig(self) -> bool:
        return (self.cfg.lambert_cue and self.pcn is not None) or (self.cfg.lambert_scn and self.scn is not None)

    def forward(self, image: torch.Tensor, mask: torch.Tensor | None = None, rig: torch.Tensor | None = None):
        if image.ndim != 4 or image.shape[1] != 3:
            raise ValueError(f"expected images of shape (B, 3, H, W), got {tuple(image.shape)}")
        if image.shape[-1] % 8 or image.shape[-2] % 8:
            raise ValueError(f"height and width must be multiples of 8 (U-Net), got {tuple(image.shape[-2:])}")
        if mask is None:  # once, for both normalisations
            mask = (image.sum(1, keepdim=True) > 0).to(image.dtype)
        x = normalise_observation(image, mask)
        if self.cfg.chroma_cue:
            x = torch.cat([x, chroma_normalise(x, mask)], 1)
        lam = None
        if self.needs_rig:
            if rig is None:
                raise ValueError("this network takes the rig (crosstalk @ light_dirs): it has net.lambert_cue")
            lam = lambertian_cue(image, mask, rig) * self.cfg.cue_gain
        coarse = self.scn(x, lam if self.cfg.lambert_scn else None) if self.scn is not None else None
        if self.pcn is None:
            return coarse, coarse
        if self.cfg.lambert_cue:
            x = torch.cat([x, lam], 1)
        return self.pcn(x, coarse), coarse


def rig_matrix(light_dirs, crosstalk) -> torch.Tensor:
    """crosstalk @ light_dirs, (..., 3, 3): what a `lambert_cue` network takes beside the image."""
    return torch.as_tensor(crosstalk, dtype=torch.float32) @ torch.as_tensor(light_dirs, dtype=torch.float32)


def widen_inputs(model: nn.Module, state: dict[str, torch.Tensor]) -> list[str]:
    """Load `state` from a network whose first layers take fewer input channels (no chroma or
    Lambertian cue) into `model` (with them): old weights fill the leading input slices, the new inputs start at
    zero, so the widened net computes exactly what the old one did until training moves them.
    Returns the widened keys; any other shape difference is an error."""
    own = model.state_dict()
    if set(own) != set(state):
        raise ValueError("the two networks have different layers")
    widened = []
    for k, v in state.items():
        if own[k].shape == v.shape:
            own[k] = v.clone()
        elif (v.ndim == 4 and own[k].ndim == 4 and own[k].shape[0] == v.shape[0]
              and own[k].shape[2:] == v.shape[2:] and own[k].shape[1] > v.shape[1]):
            w = torch.zeros_like(own[k])
            w[:, :v.shape[1]] = v
            own[k] = w
            widened.append(k)
        else:
            raise ValueError(f"{k}: shape {tuple(v.shape)} does not widen to {tuple(own[k].shape)}")
    model.load_state_dict(own)
    return widened


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def flops_per_patch(model: DualCueNet, size: int = 40) -> int:
    """Multiply-adds x 2 of one forward pass (convs and transposed convs), counted with hooks."""
    total = [0]

    def hook(m, inp, out):
        kk = m.kernel_size[0] * m.kernel_size[1]
        if isinstance(m, nn.ConvTranspose2d):  # every input pixel scatters a k x k x out/groups block
            total[0] += 2 * inp[0].numel() * kk * m.out_channels // m.groups
        else:  # every output pixel gathers k x k x in/groups
            total[0] += 2 * out.numel() * kk * m.in_channels // m.groups

    hs = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))]
    was = model.training
    model.eval()
    with torch.no_grad():
        model(torch.rand(1, 3, size, size))
    model.train(was)
    for h in hs:
        h.remove()
    return total[0]

