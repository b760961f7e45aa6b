"""The paper's losses, masked so background pixels do not count.

SCN:  L = 0.1 * L_grad + 0.9 * L_cont,  L_cont = ||n_c - n||^2,
      L_grad = ||grad(n_c) - grad(n)||^2 with grad = sqrt(dx^2 + dy^2) per component.
PCN:  L = 0.84 * (1 - SSIM(n_est, n)) + 0.16 * MAE,  MAE = mean angle (radians;
      `metrics.angular_error`, atan2(|a x b|, a . b)).
SSIM is kornia's (11x11 Gaussian window), computed on (n + 1) / 2 in [0, 1],
averaged over object pixels only.
"""
from __future__ import annotations

import torch

from msps_render.models.metrics import angular_error


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of x (B, C, H, W) over pixels where mask (B, 1, H, W) is 1, all channels."""
    m = mask.expand_as(x)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def content_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over object pixels of ||pred - gt||^2 (sum over the 3 components)."""
    return 3.0 * _masked_mean((pred - gt) ** 2, mask)


def gradient_magnitude(n: torch.Tensor) -> torch.Tensor:
    """sqrt(dx^2 + dy^2) per component by forward differences, on the (H-1, W-1) grid."""
    dx = n[..., :-1, 1:] - n[..., :-1, :-1]
    dy = n[..., 1:, :-1] - n[..., :-1, :-1]
    return torch.sqrt(dx ** 2 + dy ** 2 + 1e-12)


def gradient_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """||grad(pred) - grad(gt)||^2 over pixels whose 3 stencil pixels are all on the object."""
    gp, gg = gradient_magnitude(pred), gradient_magnitude(gt)
    m = mask[..., :-1, :-1] * mask[..., :-1, 1:] * mask[..., 1:, :-1]
    return 3.0 * _masked_mean((gp - gg) ** 2, m)


def scn_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return 0.1 * gradient_loss(pred, gt, mask) + 0.9 * content_loss(pred, gt, mask)


def mae_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return _masked_mean(angular_error(pred, gt), mask)


def ssim_map(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    import kornia

    return kornia.metrics.ssim((pred + 1) / 2, (gt + 1) / 2, window_size=11, max_val=1.0)


def masked_ssim(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return _masked_mean(ssim_map(pred, gt), mask)


def pcn_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return 0.84 * (1 - masked_ssim(pred, gt, mask)) + 0.16 * mae_loss(pred, gt, mask)


def total_loss(final: torch.Tensor, coarse: torch.Tensor | None, gt: torch.Tensor, mask: torch.Tensor,
               mode: str) -> tuple[torch.Tensor, dict]:
    """Joint training: dual = L_scn(coarse) + L_pcn(final); scn = L_scn; pcn = L_pcn."""
    parts = {}
    if mode in ("dual", "scn"):
        parts["scn"] = scn_loss(coarse, gt, mask)
    if mode in ("dual", "pcn"):
        parts["pcn"] = pcn_loss(final, gt, mask)
    return sum(parts.values()), {k: v.detach() for k, v in parts.items()}  # tensors: reading one waits for a GPU
