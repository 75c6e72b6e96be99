"""Random overlay and random convolution: statistics, shapes, reproducibility."""
import torch
import torch.nn.functional as F

from imssr.augmentations import random_conv, random_overlay


def _batch(b=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (b, 9, 20, 20), generator=g, dtype=torch.uint8)


def _pool(n=5, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, 3, 20, 20), generator=g, dtype=torch.uint8)


def test_overlay_is_the_convex_mix_with_one_image_per_sample():
    x, pool = _batch(), _pool()
    out = random_overlay(x, pool, 0.5, torch.Generator().manual_seed(3))
    assert out.shape == x.shape and out.dtype == torch.float32
    # Recover each sample's image: 2 * out - x must be one pool image, in all 3 frames.
    image = 2 * out - x.float()
    for i in range(x.shape[0]):
        frames = image[i].reshape(3, 3, 20, 20)
        assert torch.allclose(frames[0], frames[1]) and torch.allclose(frames[0], frames[2])
        assert any(torch.allclose(frames[0], p.float(), atol=1e-3) for p in pool)
    assert float(out.min()) >= 0 and float(out.max()) <= 255
    torch.testing.assert_close(out.mean(), (x.float().mean() + image.mean()) / 2)


def test_overlay_alpha_extremes_and_seed():
    x, pool = _batch(), _pool()
    assert torch.equal(random_overlay(x, pool, 0.0), x.float())
    full = random_overlay(x, pool, 1.0, torch.Generator().manual_seed(0))
    assert all(any(torch.equal(full[i, :3], p.float()) for p in pool) for i in range(x.shape[0]))
    a = random_overlay(x, pool, 0.5, torch.Generator().manual_seed(7))
    b = random_overlay(x, pool, 0.5, torch.Generator().manual_seed(7))
    assert torch.equal(a, b)


def _loop_random_conv(x, weights):
    # DMC-GB's reference formulation: one sample at a time.
    n, c, h, w = x.shape
    outs = []
    for i in range(n):
        frames = x[i:i + 1].reshape(-1, 3, h, w).float() / 255.0
        out = torch.sigmoid(F.conv2d(F.pad(frames, [1] * 4, mode="replicate"), weights[i]))
        outs.append(out.reshape(1, c, h, w) * 255.0)
    return torch.cat(outs)


def test_random_conv_matches_the_per_sample_loop():
    x = _batch()
    out = random_conv(x, torch.Generator().manual_seed(5))
    weights = torch.randn((x.shape[0] * 3, 3, 3, 3), generator=torch.Generator().manual_seed(5))
    expected = _loop_random_conv(x, weights.reshape(x.shape[0], 3, 3, 3, 3))
    assert out.shape == x.shape
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-3)
    assert float(out.min()) >= 0 and float(out.max()) <= 255
    # A sample's frames share its kernel: identical frames stay identical.
    same = x[:, :3].repeat(1, 3, 1, 1)
    o = random_conv(same, torch.Generator().manual_seed(1))
    assert torch.equal(o[:, :3], o[:, 3:6]) and torch.equal(o[:, :3], o[:, 6:])
