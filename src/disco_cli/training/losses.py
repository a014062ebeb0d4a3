"""The paper's joint loss: quadruplet loss on signatures plus lambda times the yaw KL loss."""

from __future__ import annotations

import torch
from torch.nn import functional as F


def quadruplet_loss(
    q: torch.Tensor,
    p: torch.Tensor,
    negs: torch.Tensor,
    other: torch.Tensor,
    margin1: float = 0.5,
    margin2: float = 0.2,
) -> torch.Tensor:
    """Lazy quadruplet loss (PointNetVLAD's, used by the paper) on signatures.

    q, p, other: [B, D]; negs: [B, k, D]. Squared Euclidean distances; the hardest of the
    k negatives counts ("lazy"), averaged over the batch.
    """
    d_pos = ((q - p) ** 2).sum(-1)  # [B]
    d_neg = ((q[:, None] - negs) ** 2).sum(-1)  # [B, k]
    d_other = ((other[:, None] - negs) ** 2).sum(-1)  # [B, k]
    first = F.relu(margin1 + d_pos[:, None] - d_neg).amax(dim=1)
    second = F.relu(margin2 + d_pos[:, None] - d_other).amax(dim=1)
    return (first + second).mean()


def shift_target(shift: torch.Tensor, sectors: int) -> torch.Tensor:
    """Soft one-hot [B, S] at a (possibly fractional) circular sector shift.

    An integer shift is an exact one-hot; a fractional one splits its mass linearly
    between the two neighbouring bins, whose expectation is the true shift.
    """
    shift = torch.remainder(shift.float(), sectors)
    lo = torch.floor(shift)
    frac = shift - lo
    lo = lo.long() % sectors
    hi = (lo + 1) % sectors
    target = torch.zeros(len(shift), sectors, device=shift.device)
    target.scatter_add_(1, lo[:, None], (1 - frac)[:, None])
    target.scatter_add_(1, hi[:, None], frac[:, None])
    return target


def yaw_loss(log_prob: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """KL(target || p) of the predicted shift distribution to the (soft) one-hot truth.

    Against a one-hot this equals the cross-entropy -log p(true shift); the target's
    entropy is subtracted so that a perfect prediction scores 0 for fractional shifts too.
    """
    target = shift_target(shift, log_prob.shape[-1])
    entropy = -(target * torch.log(target.clamp_min(1e-12))).sum(-1)
    return (-(target * log_prob).sum(-1) - entropy).mean()


def verify_loss(
    scores: torch.Tensor, dists: torch.Tensor, temperature: float = 0.05, length: float = 0.5
) -> torch.Tensor:
    """Cross-entropy that teaches re-ranking to pick the nearest of nearby candidates.

    scores: aligned correlations [B, n] of each query with n scans of another pass along
    its street; dists: their distances (m) to the query. The target puts weight
    exp(-(d - d_min) / length) on each candidate, so scans nearly as close as the nearest
    are not punished as if they were far.
    """
    target = torch.softmax(-(dists - dists.amin(dim=1, keepdim=True)) / length, dim=1)
    return -(target * F.log_softmax(scores / temperature, dim=1)).sum(-1).mean()
