"""Image augmentations on whole batches (vectorised, no Python loop over samples)."""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F


def random_crop(x: torch.Tensor, size: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """Independent random ``size x size`` crop per sample of ``(B, C, H, W)``.

    Offsets are drawn from ``0 .. H - size - 1`` as in the CURL / DMC-GB code (0..15 for 100 -> 84).  ``generator``
    lives on ``x``'s device: the offsets are drawn there, with no copy from the host.
    """
    b, c, h, w = x.shape
    high_y, high_x = max(h - size, 1), max(w - size, 1)
    oy = torch.randint(0, high_y, (b,), generator=generator, device=x.device)
    ox = torch.randint(0, high_x, (b,), generator=generator, device=x.device)
    return crop_at(x, oy, ox, size)


def crop_at(x: torch.Tensor, oy: torch.Tensor, ox: torch.Tensor, size: int) -> torch.Tensor:
    """Crop sample ``i`` at offsets ``(oy[i], ox[i])``.

    ``unfold`` views every ``size x size`` window without copying, so one advanced index over (sample, window row,
    window column) copies each crop as contiguous rows: several times faster than gathering every pixel with broadcast
    index tensors (``bench/crop_speed.py``), and the same values.
    """
    windows = x.unfold(2, size, 1).unfold(3, size, 1)  # (B, C, H', W', size, size)
    return windows[torch.arange(x.shape[0], device=x.device), :, oy, ox]


def center_crop(x: torch.Tensor, size: int) -> torch.Tensor:
    """Centre crop of ``(..., H, W)``: offset ``(H - size) // 2`` (8 for 100 -> 84)."""
    h, w = x.shape[-2:]
    top, left = (h - size) // 2, (w - size) // 2
    return x[..., top:top + size, left:left + size]


def random_overlay(x: torch.Tensor, images: torch.Tensor, alpha: float = 0.5,
                   generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """SODA's random overlay ``(1 - alpha) * o + alpha * image`` (paper, Appendix, Eq. overlay).

    ``x``: ``(B, 3k, S, S)`` pixels in [0, 255] (k stacked RGB frames); ``images``:
    a pool ``(N, 3, S, S)`` uint8 on ``x``'s device.  One image per sample, shared by its k frames (as DMC-GB does).
    ``generator`` lives on ``x``'s device.  Returns float pixels in [0, 255].
    """
    b, c = x.shape[:2]
    idx = torch.randint(0, images.shape[0], (b,), generator=generator, device=x.device)
    chosen = images[idx].float().repeat(1, c // 3, 1, 1)
    return torch.lerp(x.float(), chosen, alpha)


def random_conv(x: torch.Tensor, generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """SVEA's random convolution: one random 3x3 RGB->RGB kernel per sample.

    Each sample's k frames share its kernel; edges are replicate-padded and the output squashed with a sigmoid, as
    in DMC-GB, but all samples run as one grouped convolution instead of a Python loop.  ``generator`` lives on
    ``x``'s device. Returns float pixels in [0, 255].
    """
    b, c, h, w = x.shape
    k = c // 3
    weights = torch.randn((b * 3, 3, 3, 3), generator=generator, device=x.device, dtype=torch.get_default_dtype())
    # (B, k, 3, H, W) -> (k, B*3, H, W): frames as the batch, samples as groups.
    frames = (x.float() / 255.0).reshape(b, k, 3, h, w).transpose(0, 1).reshape(k, b * 3, h, w)
    out = F.conv2d(F.pad(frames, (1, 1, 1, 1), mode="replicate"), weights, groups=b)
    out = torch.sigmoid(out) * 255.0
    return out.reshape(k, b, 3, h, w).transpose(0, 1).reshape(b, c, h, w)
