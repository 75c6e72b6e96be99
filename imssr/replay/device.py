"""Replay frames on the device (``train.replay_device``): the tensor store, and where ``auto``
puts the frames.

:class:`TensorFrameReplayBuffer` is :class:`~imssr.replay.buffer.FrameReplayBuffer` with the
frames in a torch uint8 tensor on a device: a batch's windows are indexed and stacked there (and
cropped there by the agent), so no frame crosses to the device at sample time.  What decides a
batch stays on the host, as in the host store: the sampling generator, the episode bookkeeping
that tells which slots are valid, the per-slot action, reward and discount, and the physics
states.  One copy per batch moves the frame slots and those fields to the device.  Both stores
therefore draw the same indices and give the same batches for one seed, and save and load the
same files, so a run saved with one resumes with the other, exactly.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from imssr.errors import ImssrError
from imssr.integrity import HashingWriter
from imssr.replay.buffer import READ_CHUNK, DiskFrameReplayBuffer, FrameReplayBuffer, read_hashed

REPLAY_DEVICE_MARGIN_BYTES = 4 * 10**9
"""GPU memory that ``auto`` keeps free beside the frames for the rest of the run: the networks
and their Adam state (tens of MB), the largest update's activations (an 11-layer preset with
grad through 256 crops of 84 px, SVEA's two views or PAD's o and o': about 1 GB in float32),
cuDNN workspaces, the caching allocator's slack and the renderers' EGL contexts.  4 GB is about
twice their sum, so a run that fits is not the one that runs out of memory at its first update."""

SAVE_CHUNK = 1 << 24
"""Bytes of frames copied to the host per write when saving from the device."""


class TensorFrameReplayBuffer(FrameReplayBuffer):
    """The frame store as a torch uint8 tensor on ``device`` (any device: on the CPU it runs the
    same code, which is how it is tested without a GPU).

    Args:
        device: where the frames live and batches are gathered; the other arguments are
            :class:`~imssr.replay.buffer.FrameReplayBuffer`'s.
    """

    def __init__(self, *args, device: str | torch.device = "cpu", **kwargs):
        self.device = torch.device(device)
        super().__init__(*args, **kwargs)

    def host_nbytes_expected(self) -> int:
        on_host = self.device.type == "cpu"
        return self.nbytes_expected() - (0 if on_host else self.capacity * self.frame_nbytes())

    def _allocate_frames(self) -> torch.Tensor:
        if self.device.type == "cpu":
            # numpy's zeros are mapped lazily (torch.zeros would touch every page now).
            return torch.from_numpy(super()._allocate_frames())
        try:
            return torch.zeros((self.capacity, *self.frame_shape), dtype=torch.uint8, device=self.device)
        except torch.cuda.OutOfMemoryError:
            raise ImssrError(
                f"cannot allocate {self.capacity * self.frame_nbytes() / 1e9:.1f} GB of replay frames on "
                f"{self.device} ({self.capacity} transitions); use --set train.replay_device=cpu or "
                "lower the replay capacity (--replay-capacity)") from None

    def _write_frame(self, slot: int, frame: np.ndarray) -> None:
        src = torch.from_numpy(np.ascontiguousarray(frame, dtype=np.uint8))
        if self.device.type == "cuda":
            # From page-locked memory the copy does not wait for the device (the caching host
            # allocator keeps the block until the copy has run).
            src = src.pin_memory()
        self.frames[slot].copy_(src, non_blocking=True)

    # -- sampling ----------------------------------------------------------------
    def gather_batch(self, idx: np.ndarray, device: torch.device) -> dict[str, torch.Tensor]:
        """The frame slots of the windows and the transition fields cross to the store's device in
        one ``non_blocking`` copy (from pinned memory on CUDA); the windows are gathered there."""
        idx = np.asarray(idx, dtype=np.int64)
        b = len(idx)
        packing = self._packing(b, torch.int64, (b * (self.frame_stack + 1),))
        host = packing.host_buffer(pin=self.device.type == "cuda")
        slots, *fields = packing.views(host)
        slots.copy_(torch.from_numpy(self.stack_indices(idx).reshape(-1)))
        self._gather_fields(idx, *fields)
        slots, *fields = packing.views(host.to(self.device, non_blocking=True))
        frames = self.frames.index_select(0, slots)
        # A no-op when the agent is on the store's device (as the trainer places it).
        return self._batch(*(x.to(device) for x in (frames, *fields)))

    # -- persistence -------------------------------------------------------------
    def _write_slots(self, writer: HashingWriter, slot: int, count: int) -> None:
        """The slots' frames, copied from the device in pieces (peak host memory: one piece)."""
        rows = max(1, SAVE_CHUNK // self.frame_nbytes())
        for start in range(slot, slot + count, rows):
            piece = self.frames[start:min(start + rows, slot + count)].cpu()  # on the CPU: the tensor itself
            writer.write(memoryview(piece.numpy()).cast("B"))

    def _read_slots(self, fh, h, slot: int, count: int, fpath: str) -> None:
        total = count * self.frame_nbytes()
        staging = torch.empty(max(1, min(total, READ_CHUNK)), dtype=torch.uint8,
                              pin_memory=self.device.type == "cuda")
        view = memoryview(staging.numpy())
        flat = self.frames[slot:slot + count].view(-1)
        for start in range(0, total, len(view)):
            size = min(len(view), total - start)
            read_hashed(fh, h, view[:size], fpath)
            flat[start:start + size].copy_(staging[:size])  # blocking: the staging is refilled next


@dataclass(frozen=True)
class ReplayPlacement:
    """Where the replay frames live, and why."""

    device: torch.device
    """The CPU (the numpy host store) or a CUDA device (:class:`TensorFrameReplayBuffer`)."""
    reason: Optional[str] = None
    """One line saying what ``auto`` chose and why; None where there was nothing to choose."""
    disk: bool = False
    """The frames in a memory-mapped file on local disk (``train.replay_device=disk``,
    :class:`~imssr.replay.buffer.DiskFrameReplayBuffer`); ``device`` is then the CPU."""


def choose_replay_device(setting: str, agent_device: torch.device, frames_nbytes: int,
                         free_nbytes: Optional[int],
                         margin_nbytes: int = REPLAY_DEVICE_MARGIN_BYTES,
                         share: float = 1.0, total_nbytes: Optional[int] = None) -> ReplayPlacement:
    """Where ``train.replay_device = setting`` puts ``frames_nbytes`` of frames for an agent on
    ``agent_device`` whose device has ``free_nbytes`` free of ``total_nbytes`` (None: not a CUDA
    device).

    ``cpu``: the host.  ``disk``: a file on local disk, mapped into host memory.  ``cuda``: the
    agent's GPU (the agent must be on one).  ``auto``: the
    agent's GPU when the room it has there holds the frames plus ``margin_nbytes`` for the model
    (:data:`REPLAY_DEVICE_MARGIN_BYTES`), else the host; a CPU agent keeps them on the host.  The
    room is the free memory, or with ``share`` < 1 (``train.gpu_share``: runs sharing the GPU)
    that fraction of the total, at most what is free: the same for runs that start together,
    whose frames are not allocated yet when each one looks."""
    if setting == "cpu":
        return ReplayPlacement(torch.device("cpu"))
    if setting == "disk":
        return ReplayPlacement(torch.device("cpu"), disk=True)
    if setting == "cuda":
        if agent_device.type != "cuda":
            raise ImssrError(f"train.replay_device=cuda needs the agent on a GPU, but train.device is "
                             f"{agent_device}; use --device cuda or --set train.replay_device=cpu")
        return ReplayPlacement(agent_device)
    if setting != "auto":
        raise ImssrError(f"train.replay_device must be one of cpu, cuda, auto, disk, got {setting!r}")
    if agent_device.type != "cuda" or free_nbytes is None:
        return ReplayPlacement(torch.device("cpu"))
    need, gb = frames_nbytes + margin_nbytes, 1e9
    if share < 1 and total_nbytes is not None:
        room = min(free_nbytes, int(share * total_nbytes))
        where = (f"{room / gb:.1f} GB for this run on {agent_device}, its share {share:g} of "
                 f"{total_nbytes / gb:.1f} GB")
    else:
        room, where = free_nbytes, f"{free_nbytes / gb:.1f} GB free on {agent_device}"
    sizes = f"{frames_nbytes / gb:.1f} GB of frames + {margin_nbytes / gb:.1f} GB for the model, {where}"
    if room >= need:
        return ReplayPlacement(agent_device, f"imssr: replay frames on {agent_device} "
                                             f"(train.replay_device=auto: {sizes})")
    return ReplayPlacement(torch.device("cpu"), f"imssr: replay frames in host memory, the GPU lacks room "
                                                f"(train.replay_device=auto: {sizes})")


def replay_placement(setting: str, agent_device: torch.device, frames_nbytes: int,
                     share: float = 1.0, margin_nbytes: int = REPLAY_DEVICE_MARGIN_BYTES) -> ReplayPlacement:
    """:func:`choose_replay_device` with this machine's CUDA state (free and total memory from
    ``torch.cuda.mem_get_info``)."""
    if setting == "cuda" and not torch.cuda.is_available():
        raise ImssrError("train.replay_device=cuda requested but CUDA is not available; "
                         "use --set train.replay_device=cpu")
    free = total = None
    if agent_device.type == "cuda" and setting == "auto":
        if agent_device.index is None:  # name the GPU the message speaks of
            agent_device = torch.device("cuda", torch.cuda.current_device())
        free, total = torch.cuda.mem_get_info(agent_device)
    return choose_replay_device(setting, agent_device, frames_nbytes, free, margin_nbytes=margin_nbytes, share=share,
                                total_nbytes=total)


def make_replay_buffer(device: torch.device, capacity: int, frame_shape: tuple[int, int, int], action_dim: int,
                       frame_stack: int = 3, seed: int | np.random.SeedSequence = 0,
                       physics_dim: int = 0, frames_file: Optional[str] = None,
                       reserve_slots: int = 0) -> FrameReplayBuffer:
    """The host store for frames on the CPU (in the memory-mapped ``frames_file`` when given, with
    disk space for ``reserve_slots`` frames set aside), the tensor store for frames on a GPU."""
    if frames_file is not None:
        return DiskFrameReplayBuffer(capacity, frame_shape, action_dim, frame_stack, seed=seed,
                                     physics_dim=physics_dim, path=frames_file, reserve_slots=reserve_slots)
    if device.type == "cpu":
        return FrameReplayBuffer(capacity, frame_shape, action_dim, frame_stack, seed=seed, physics_dim=physics_dim)
    return TensorFrameReplayBuffer(capacity, frame_shape, action_dim, frame_stack, seed=seed,
                                   physics_dim=physics_dim, device=device)
