"""Mixed precision (``agent.precision``) and the device switches of an agent.

``bf16`` runs the forward passes under :func:`torch.autocast` with bfloat16 on the agent's device type (CPU or CUDA
alike); weights, gradients and Adam's state stay float32.  Pieces whose rounding matters run in float32 inside
:func:`full_precision` regions; with ``fp32`` no autocast context is ever entered, so :func:`full_precision` is a
no-op and the float32 path is unchanged.
"""
from __future__ import annotations

import contextlib
import functools
import sys
from typing import ContextManager, Optional

import torch
import torch.nn.functional as F
from torch import nn

from imssr.files import read_small


def autocast(device: torch.device, precision: str) -> ContextManager:
    """The context of an agent's forward passes: bfloat16 autocast for ``bf16``, else nothing."""
    if precision == "bf16":
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def full_precision(x: torch.Tensor) -> ContextManager:
    """A float32 region inside an autocast one (on ``x``'s device type), for the pieces that stay
    float32; a no-op context when no autocast is active.  Cast inputs with ``.float()`` inside
    it: the ops themselves no longer cast, and ``.float()`` of a float32 tensor is the tensor."""
    if torch.is_autocast_enabled(x.device.type):
        return torch.autocast(device_type=x.device.type, enabled=False)
    return contextlib.nullcontext()


def upcast(x: torch.Tensor) -> torch.Tensor:
    """``x`` in at least float32: bfloat16 and float16 are cast up, float32 and float64 kept (an
    agent in float64, as the member-batch equivalence tests run it, stays float64)."""
    return x if x.dtype in (torch.float32, torch.float64) else x.float()


class FP32LayerNorm(nn.LayerNorm):
    """LayerNorm computed in float32 under autocast: its mean and variance over a bfloat16 row
    lose the small differences it exists to rescale (same parameters and state dict as
    :class:`torch.nn.LayerNorm`)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with full_precision(x):
            return super().forward(upcast(x))


class FP32BatchNorm1d(nn.BatchNorm1d):
    """BatchNorm1d computed in float32 under autocast, for the same reason as
    :class:`FP32LayerNorm` (batch statistics)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with full_precision(x):
            return super().forward(upcast(x))


class FrozenBF16:
    """The forward of a frozen ``nn.Linear`` or ``nn.Conv2d`` (weights without grad: target networks, RND's random
    target) that keeps bfloat16 copies of its weight and bias for bf16 autocast.  Autocast caches the casts of
    weights that require grad only, so it would cast these again at every call; the copies are made again only when
    the weights change (the version counters: an EMA step, a loaded state dict).  The same values as autocast's
    cast, so the same numbers; outside bf16 autocast, the layer's own forward."""

    def __init__(self, layer: nn.Linear | nn.Conv2d):
        self.layer = layer
        self.key: Optional[tuple] = None
        self.copies: tuple[Optional[torch.Tensor], ...] = ()

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        layer = self.layer
        device = x.device.type
        if not torch.is_autocast_enabled(device) or torch.get_autocast_dtype(device) != torch.bfloat16:
            return type(layer).forward(layer, x)
        params = (layer.weight, layer.bias)
        key = tuple(None if p is None else (p.data_ptr(), p._version) for p in params)
        if key != self.key:
            self.copies = tuple(None if p is None else p.detach().to(torch.bfloat16) for p in params)
            self.key = key
        weight, bias = self.copies
        if isinstance(layer, nn.Conv2d):
            return layer._conv_forward(x, weight, bias)
        return F.linear(x, weight, bias)


def cache_frozen_weights(*modules: nn.Module) -> int:
    """Give every frozen ``nn.Linear`` and ``nn.Conv2d`` (no parameter requires grad) under
    ``modules`` a :class:`FrozenBF16` forward; returns how many layers."""
    layers = {id(m): m for module in modules for m in module.modules()
              if type(m) in (nn.Linear, nn.Conv2d) and not any(p.requires_grad for p in m.parameters())}
    for layer in layers.values():
        layer.forward = FrozenBF16(layer)
    return len(layers)


def adam(params, lr: float, betas: tuple[float, float] = (0.9, 0.999), fused: bool = False) -> torch.optim.Adam:
    """torch's Adam, fused (``agent.fused_adam``: one kernel per group on CUDA, the last bits of rounding differ) or
    torch's default implementation (the foreach kernels on CUDA, the per-tensor loop on CPU; foreach is
    bit-identical there and gains nothing).  Under ``agent.cuda_graphs`` the agent switches its optimisers to
    ``capturable`` before recording (:func:`imssr.agents.graphs.set_capturable`)."""
    return torch.optim.Adam(params, lr=lr, betas=betas, fused=True if fused else None)


def optimizer_step(loss: torch.Tensor, *optimizers: torch.optim.Optimizer) -> None:
    """Backpropagate ``loss`` and step each optimiser on its parameters' fresh gradients.

    Outside autocast: the backward pass runs each op in the dtype its forward used, and the optimiser updates the
    float32 weights and state in float32 (torch's advice: autocast wraps forward passes and losses only)."""
    for opt in optimizers:
        opt.zero_grad(set_to_none=True)
    # Only the stepped parameters' gradients: autograd then skips the weight gradients that no
    # optimiser here reads (the actor's loss goes through the critic's Q heads for dQ/da, not for
    # the heads' weights), and each stepped gradient is computed as a full backward computes it.
    stepped = [p for opt in optimizers for group in opt.param_groups for p in group["params"] if p.requires_grad]
    with full_precision(loss):
        loss.backward(inputs=stepped)
        for opt in optimizers:
            opt.step()
    # Autocast keeps its bfloat16 casts of the weights until the outermost autocast region ends,
    # without looking at their versions: the passes after this step in the same update (the
    # actor's on the critic's trunk, the auxiliary task's) would read the weights from before it.
    torch.clear_autocast_cache()


def cpu_features(cpuinfo: str) -> tuple[str, frozenset[str]]:
    """``(vendor, flags)`` of the CPU that ``cpuinfo`` (the text of /proc/cpuinfo) describes: x86's
    ``vendor_id`` (``GenuineIntel``, ``AuthenticAMD``; empty elsewhere) and its ``flags`` (Arm:
    ``Features``)."""
    vendor, flags = "", set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        key = key.strip().lower()
        if key == "vendor_id" and not vendor:
            vendor = value.strip()
        elif key in ("flags", "features"):
            flags.update(value.split())
    return vendor, frozenset(flags)


def native_bf16(cpuinfo: str) -> bool:
    """Whether the CPU that ``cpuinfo`` (the text of /proc/cpuinfo) describes computes bfloat16
    natively: x86 ``avx512_bf16`` or AMX (``amx_bf16``), Arm ``bf16``."""
    return bool(cpu_features(cpuinfo)[1] & {"avx512_bf16", "amx_bf16", "bf16"})


def bf16_slowdown(vendor: str, flags: frozenset[str]) -> Optional[str]:
    """Why ``agent.precision=bf16`` is expected to run slower than float32 on a CPU of ``vendor`` with ``flags``
    (:func:`cpu_features`): ``"no-amx"`` (``avx512_bf16`` on a CPU that is not AMD's, without AMX) or ``"emulated"``
    (no native bfloat16); None where it is expected to gain or nothing is known.

    Measured per update (docs/performance.md, "Mixed precision"): AMD Zen 4 (``avx512_bf16``) 0.42-0.46x of
    float32's time, an Intel Xeon with ``avx512_bf16`` but without AMX 1.14-1.23x, emulated bfloat16 about 5x.
    Intel CPUs with AMX (``amx_bf16``) gain; Arm's ``bf16`` is native and not measured."""
    if flags & {"amx_bf16", "bf16"}:
        return None
    if "avx512_bf16" in flags:
        return None if vendor == "AuthenticAMD" else "no-amx"
    return "emulated"


@functools.cache
def cpu_info() -> Optional[str]:
    """The text of this machine's /proc/cpuinfo; None where there is none."""
    return read_small("/proc/cpuinfo")


_warned_slow_bf16 = False


def warn_if_bf16_is_slow(device: torch.device, precision: str) -> Optional[str]:
    """Print, once per process, that bf16 will be slower than float32 on this CPU
    (:func:`bf16_slowdown`); return the line, or None when there is nothing to say."""
    global _warned_slow_bf16
    info = cpu_info() if precision == "bf16" and device.type == "cpu" else None
    why = None if info is None else bf16_slowdown(*cpu_features(info))
    if why is None:
        return None
    cpu = {"no-amx": "with avx512_bf16 but without AMX (AMD Zen 4 and Intel CPUs with AMX gain; an Intel "
                     "Xeon without AMX ran bf16 updates at 1.14-1.23x of fp32's time)",
           "emulated": "without native bfloat16 (no avx512_bf16/AMX; torch sees "
                       f"{torch.backends.cpu.get_cpu_capability()})"}[why]
    line = f"imssr: warning: agent.precision=bf16 on a CPU {cpu}: expect it slower than fp32 here"
    if not _warned_slow_bf16:
        _warned_slow_bf16 = True
        print(line, file=sys.stderr)
    return line


def configure_process(cfg, device: torch.device) -> None:
    """Set the process-wide switches a run's agent settings ``cfg`` (``agent.*``) ask for on
    ``device`` (:func:`configure_cuda`), and say once if bf16 will be slow on this CPU.  Called by
    whoever builds a run's agents (:func:`imssr.training.build.build_agent`), not by an agent's
    constructor; calling it again with the same settings changes nothing."""
    warn_if_bf16_is_slow(device, cfg.precision)
    configure_cuda(device, cfg.tf32)


def configure_cuda(device: torch.device, tf32: str) -> None:
    """On CUDA: cuDNN picks its fastest convolution algorithms for the (fixed) input shapes, and TensorFloat-32 as
    ``tf32`` (``agent.tf32``) says: ``default`` sets PyTorch's own defaults (TF32 in cuDNN convolutions, not in
    matmuls), ``true`` allows it in both, ``false`` in neither.  The switches are process-wide.  No-op on CPU."""
    if device.type != "cuda":
        return
    torch.backends.cudnn.benchmark = True
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = tf32_switches(tf32)


def tf32_switches(tf32: str) -> tuple[bool, bool]:
    """``(matmul, cudnn)``: whether matmuls and cuDNN convolutions may use TensorFloat-32 under
    ``agent.tf32 = tf32``."""
    return {"default": (False, True), "true": (True, True), "false": (False, False)}[tf32]
