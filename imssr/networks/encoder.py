"""Pixel encoder: a convolutional trunk shared by critic and actor, and projections.

Following the CURL / DMC-GB code bases, the critic owns the convolutional trunk
and a ``Linear -> LayerNorm`` projection; the actor reads the trunk's output with
gradients stopped and trains only its own projection.
"""
from __future__ import annotations

import contextlib
import functools
import weakref
from typing import Iterator

import torch
from torch import nn

from imssr.precision import FP32LayerNorm
from imssr.settings import conv_output_size


def conv_stack(filters: int, num_layers: int, final_relu: bool = False) -> nn.Sequential:
    """``num_layers`` stride-1 3x3 convolutions of ``filters`` channels, each after a ReLU.

    The ReLU comes first (DMC-GB's layout): a stack continues a convolution's output, so
    ReLUs stand between convolutions and none follows the last one unless ``final_relu``
    (:class:`ConvTrunk`'s, for the encoder's output).
    """
    layers: list[nn.Module] = []
    for i in range(num_layers):
        # In place after the stack's own convolutions: a convolution's backward needs its
        # input, not its output, and ReLU's backward reads its own output.  Not the first:
        # the stack's input may have other readers (PAD's head and the critic's read the
        # same shared features).
        layers += [nn.ReLU(inplace=i > 0), nn.Conv2d(filters, filters, 3, stride=1)]
    if final_relu:
        layers.append(nn.ReLU(inplace=num_layers > 0))
    return nn.Sequential(*layers)


_PIXELS: dict[tuple, torch.Tensor] = {}
"""uint8 frames already converted by :func:`pixels`, by (the frames' id, version, dtype, layout);
an entry lives as long as its frames (a finaliser removes it)."""

ONE_PASS_DEVICES = {"cuda"}
"""Device types whose conversion runs in :func:`one_pass`, where it is bound by its bytes; a
CPU runs :func:`three_passes`, which is faster there (``bench/pixels_speed.py``)."""


def pixels(obs: torch.Tensor, dtype: torch.dtype, fmt: torch.memory_format, reuse: bool = True) -> torch.Tensor:
    """uint8 pixels -> floats in [0, 1] in layout ``fmt``: the same values as ``obs.float() /
    255``, computed once per distinct input.  An update passes the same frames through several
    trunks (o through the critic's and, after its step, the actor's; o' through the online and
    the target trunk), and each conversion writes four bytes per pixel; the float copy is only
    ever read (the first layer is a convolution, whose input nothing changes in place), so every
    trunk may read the same one.  ``reuse=False`` (inside torch.compile, where a tensor's identity
    means nothing) converts afresh."""
    if not reuse:
        return three_passes(obs, dtype, fmt)
    key = (id(obs), obs._version, dtype, fmt)
    hit = _PIXELS.get(key)
    if hit is None:
        convert = one_pass if obs.device.type in ONE_PASS_DEVICES else three_passes
        hit = _PIXELS[key] = convert(obs, dtype, fmt)
        weakref.finalize(obs, _PIXELS.pop, key, None)
    return hit


def three_passes(obs: torch.Tensor, dtype: torch.dtype, fmt: torch.memory_format) -> torch.Tensor:
    """:func:`pixels`' conversion as a relayout of the 1-byte pixels (not of the 4-byte floats),
    a cast and an in-place divide: on a CPU faster than :func:`one_pass`, whose mixed-type divide
    there casts into a float temporary first (``bench/pixels_speed.py``)."""
    return obs.contiguous(memory_format=fmt).to(dtype).div_(255.0)


def one_pass(obs: torch.Tensor, dtype: torch.dtype, fmt: torch.memory_format) -> torch.Tensor:
    """:func:`pixels`' conversion as one divide that reads each byte and writes its float in
    layout ``fmt``: one kernel instead of three, and 5 bytes moved per pixel instead of 15 (on
    CUDA, where the conversion is bound by its bytes).  A 0-dim divisor of ``dtype`` makes it
    divide in ``dtype``, as ``obs.to(dtype) / 255`` does: the values of :func:`three_passes`."""
    out = torch.empty(obs.shape, dtype=dtype, device=obs.device, memory_format=fmt)
    return torch.div(obs, _divisor(dtype), out=out)


@functools.cache
def _divisor(dtype: torch.dtype) -> torch.Tensor:
    """255 as a 0-dim CPU tensor of ``dtype`` (to a CUDA kernel, a scalar: no copy), on the CPU
    whatever torch's default device; made once per dtype."""
    return torch.tensor(255.0, dtype=dtype, device="cpu")


class ConvTrunk(nn.Module):
    """``num_layers`` 3x3 convolutions of ``filters`` channels with a ReLU between each two.

    ``final_relu`` adds one after the last convolution too (official CURL); DMC-GB, whose
    encoder the authors ran for every algorithm, has none.  The shared layers' output
    (:meth:`shared_features`) is a convolution's output without its ReLU; the head, like a
    head of an auxiliary task built on the same features (PAD), starts with one.

    The first ``num_layers - head_layers`` (``convs``) may be shared with an
    auxiliary task that builds a head of its own (PAD); the last ``head_layers``
    (``head``) belong to the RL encoder only (DMC-GB's shared / head CNN split).
    Input: uint8 or float pixels in [0, 255], ``(B, C, S, S)``; output: the
    flattened feature map ``(B, filters * s * s)``, always in (C, H, W) order so
    that weights do not depend on ``channels_last``.

    ``channels_last`` runs the convolutions on NHWC activations and weights:
    oneDNN's 32-channel 3x3 kernels run a forward pass about 1.2x faster in that
    layout on CPU (``bench/conv_layout.py``), and cuDNN prefers it too.
    """

    def __init__(self, in_channels: int, image_size: int, num_layers: int = 4, filters: int = 32,
                 head_layers: int = 0, channels_last: bool = True, final_relu: bool = False):
        super().__init__()
        out = conv_output_size(image_size, num_layers)
        if out < 1:
            raise ValueError(f"{num_layers} conv layers leave no pixels of a {image_size}px input")
        if not 0 <= head_layers < num_layers:
            raise ValueError(f"head_layers must be in [0, {num_layers}), got {head_layers}")
        self.convs = nn.Sequential(nn.Conv2d(in_channels, filters, 3, stride=2),
                                   *conv_stack(filters, num_layers - 1 - head_layers))
        self.head = conv_stack(filters, head_layers, final_relu)
        self.filters, self.head_layers, self.final_relu = filters, head_layers, final_relu
        self.channels_last = channels_last
        self.out_dim = filters * out * out
        if channels_last:
            # Weights in NHWC too: as fast as NHWC activations alone for 4 layers and
            # a few percent faster for 11 (bench/conv_layout.py).
            self.to(memory_format=torch.channels_last)

    def prepare(self, obs: torch.Tensor) -> torch.Tensor:
        """Pixels in [0, 255] -> floats in [0, 1], in the trunk's memory layout; once per
        distinct uint8 input (:func:`pixels`)."""
        fmt = torch.channels_last if self.channels_last else torch.contiguous_format
        dtype = self.convs[0].weight.dtype  # float32; float64 for an agent cast to it
        if obs.dtype == torch.uint8:
            return pixels(obs, dtype, fmt, reuse=not torch.compiler.is_compiling())
        return (obs.to(dtype) / 255.0).contiguous(memory_format=fmt)

    def shared_features(self, obs: torch.Tensor) -> torch.Tensor:
        """Output of the shared layers, ``(B, filters, s', s')``, before the RL head."""
        return self.convs(self.prepare(obs))

    def head_features(self, features: torch.Tensor) -> torch.Tensor:
        """The RL head on :meth:`shared_features`' output, flattened: ``(B, out_dim)``."""
        return self.head(features).flatten(1)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.head_features(self.shared_features(obs))

    def compile(self, *args, **kwargs) -> None:
        """``torch.compile`` the two passes callers make (:meth:`shared_features`, then
        :meth:`head_features`; :meth:`forward` is both), in place: the state dict keeps its keys.
        Compiling ``convs`` or ``head`` themselves would capture nothing: Dynamo does not trace
        the forward of a ``torch.nn`` container called as the compiled frame."""
        for name in ("shared_features", "head_features"):
            setattr(self, name, torch.compile(getattr(self, name), *args, **kwargs))


class Projection(nn.Module):
    """``Linear -> LayerNorm`` (``-> tanh`` optionally) from trunk features to latents."""

    def __init__(self, in_dim: int, out_dim: int, tanh: bool = False):
        super().__init__()
        self.fc = nn.Linear(in_dim, out_dim)
        self.ln = FP32LayerNorm(out_dim)
        self.tanh = tanh
        self.out_dim = out_dim

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        z = self.ln(self.fc(h))
        return torch.tanh(z) if self.tanh else z


class Encoder(nn.Module):
    """Trunk followed by a projection: pixels -> latent ``z``."""

    def __init__(self, trunk: ConvTrunk, feature_dim: int, tanh: bool = False):
        super().__init__()
        self.trunk = trunk
        self.projection = Projection(trunk.out_dim, feature_dim, tanh)
        self.out_dim = feature_dim

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.projection(self.trunk(obs))


_shapes_only = False


@contextlib.contextmanager
def shapes_only() -> Iterator[None]:
    """Inside the block :func:`weight_init` does nothing: for networks built only for their shapes
    (a training's memory plan counts an agent's parameters), whose orthogonal initialisation (a
    QR decomposition per weight) would take seconds for the presets' 1024-wide layers."""
    global _shapes_only
    before, _shapes_only = _shapes_only, True
    try:
        yield
    finally:
        _shapes_only = before


def weight_init(m: nn.Module) -> None:
    """Orthogonal init for linear layers, delta-orthogonal for convolutions (as CURL)."""
    if _shapes_only:
        return
    if isinstance(m, nn.Linear):
        nn.init.orthogonal_(m.weight.data)
        m.bias.data.fill_(0.0)
    elif isinstance(m, nn.Conv2d):
        m.weight.data.fill_(0.0)
        m.bias.data.fill_(0.0)
        mid = m.weight.size(2) // 2
        gain = nn.init.calculate_gain("relu")
        nn.init.orthogonal_(m.weight.data[:, :, mid, mid], gain)
