"""Image augmentations on whole uint8 batches (one gather, no Python loop)."""
from __future__ import annotations

from typing import Optional

import torch


def random_crop(x: torch.Tensor, size: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """Independent random ``size x size`` crop per sample of ``(B, C, H, W)``.

    Offsets are drawn from ``0 .. H - size - 1`` as in the CURL / DMC-GB code
    (0..15 for 100 -> 84).  ``generator`` is a CPU generator.
    """
    b, c, h, w = x.shape
    high_y, high_x = max(h - size, 1), max(w - size, 1)
    oy = torch.randint(0, high_y, (b,), generator=generator).to(x.device)
    ox = torch.randint(0, high_x, (b,), generator=generator).to(x.device)
    return crop_at(x, oy, ox, size)


def crop_at(x: torch.Tensor, oy: torch.Tensor, ox: torch.Tensor, size: int) -> torch.Tensor:
    """Crop sample ``i`` at offsets ``(oy[i], ox[i])``."""
    b, c = x.shape[:2]
    ar = torch.arange(size, device=x.device)
    rows = (oy[:, None] + ar)[:, None, :, None]
    cols = (ox[:, None] + ar)[:, None, None, :]
    bi = torch.arange(b, device=x.device)[:, None, None, None]
    ci = torch.arange(c, device=x.device)[None, :, None, None]
    return x[bi, ci, rows, cols]


def center_crop(x: torch.Tensor, size: int) -> torch.Tensor:
    """Centre crop of ``(..., H, W)``: offset ``(H - size) // 2`` (8 for 100 -> 84)."""
    h, w = x.shape[-2:]
    top, left = (h - size) // 2, (w - size) // 2
    return x[..., top:top + size, left:left + size]
