"""The memory plan of a training: what its runs will hold in host memory, on the GPU and on local
disk, reckoned from their configs before any run directory is written or any run's agent is built
(:func:`memory_plan`, which :func:`imssr.training.entry.train` makes), and refused in one line
with the arithmetic and the ways out when the machine lacks it.

Per run (a seed of ``imssr train --seeds``, a run directory of ``--runs``, or a run alone):

- replay frames: the slots the run will fill (``train.replay_capacity``, or fewer when the budget
  ends first: one slot per agent step and one more per episode) times one frame's bytes
  (``3 x image_size^2``), in host memory (``train.replay_device=cpu``), on the GPU (``cuda``) or
  in a file on local disk (``disk``);
- the replay's other arrays (action, reward, discount, step in episode, physics state, agent
  step: :meth:`FrameReplayBuffer.bytes_per_slot`), always in host memory;
- the agent: its weights, gradients and Adam moments (four float32 copies of its trainable
  parameters, one of the rest), and one update's activations (the encoder's feature maps, kept
  for the backward pass, of the RL and the auxiliary batch), on the agent's device, for every
  member of a batch: on a GPU its members update side by side (each on a stream of its own); on
  the CPU they update one after another, yet the process grows by about one update's activations
  per member (measured: docs/performance.md), so they are counted per member there too;
- the rest of the run in host memory (:data:`RUN_HOST_BYTES`): its training and evaluation
  environments with their renderers, frame stacks and the buffers of its loop, measured.

Host memory is compared with what the kernel says is available (``MemAvailable``) and, under an
address-space limit (``ulimit -v``), the whole replay (its arrays are mapped at their full
capacity) with what the limit leaves; GPU memory with what is free (or the run's share,
``train.gpu_share``); a frames file with the free space of its file system.

The plan also decides, once for all the runs, where their replay frames go, which each run's
trainer is handed (:class:`~imssr.training.loop.Trainer`): for ``train.replay_device=auto`` on the
GPU when every run's frames fit there beside the agents and
:data:`~imssr.replay.device.REPLAY_DEVICE_MARGIN_BYTES` (for a run alone: the rule of
:func:`~imssr.replay.device.choose_replay_device`), else in host memory.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Sequence

import torch

from imssr.config import RunConfig
from imssr.settings import conv_output_size
from imssr.envs.tasks import task_dims
from imssr.errors import ImssrError
from imssr.memlimit import address_space_in_use, address_space_limit, raise_limit_text
from imssr.networks import shapes_only
from imssr.replay import ReplayPlacement, available_memory_bytes, replay_placement
from imssr.replay.device import REPLAY_DEVICE_MARGIN_BYTES
from imssr.rundir import RunDir

GB = 1e9

SIMULATOR_STEPS = 1000
"""Simulator steps of an episode (every task of the paper): episodes of ``1000 / action_repeat``
agent steps, each one slot more than its transitions."""


RUN_HOST_BYTES = 140_000_000
"""Host memory a run holds beyond its replay and its agent: its environments (training and
evaluation, each with a MuJoCo renderer and its GL context), frame stacks and the loop's buffers.
Measured as the growth of a ``--seeds 1-N`` process's peak resident memory per seed, less the
replay, agent and activation bytes the plan counts (docs/performance.md, "Memory a run holds
beside replay and agent"): 136 MB at the tiny sizes (64-px frames and shadows) and 99 MB at the
presets' (100-px frames, 512-px shadows), on the CPU; one constant, the larger with some room."""


@dataclass(frozen=True)
class RunNeeds:
    """What one run will hold (see the module's doc)."""

    slots: int
    """Replay slots it fills: its capacity, or fewer when its budget ends first."""
    capacity: int
    """Replay slots it maps (``train.replay_capacity``): what an address-space limit counts."""
    frame_bytes: int
    """Bytes of one stored frame."""
    other_bytes: int
    """Bytes of a slot's other fields."""
    agent_bytes: int
    """The agent's weights, gradients and Adam moments."""
    activation_bytes: int
    """One update's activations (the encoder's feature maps kept for the backward pass)."""

    @property
    def frames_bytes(self) -> int:
        return self.slots * self.frame_bytes

    @property
    def others_bytes(self) -> int:
        return self.slots * self.other_bytes


def replay_slots(cfg: RunConfig) -> int:
    """The replay slots a run of ``cfg`` fills by the end of its budget: one per agent step and
    one more per episode (its first frame), at most ``train.replay_capacity``."""
    steps = cfg.total_steps
    episode = max(1, SIMULATOR_STEPS // cfg.env.action_repeat)
    return min(cfg.train.replay_capacity, steps + math.ceil(steps / episode) + 1)


def run_needs(cfg: RunConfig) -> RunNeeds:
    """What a run of ``cfg`` will hold, from its config alone (nothing is built but one agent, to
    count its parameters)."""
    action_dim, physics_dim = task_dims(cfg.env.task)
    other = 4 * action_dim + 4 + 4 + 4 + (8 * physics_dim + 4)  # as FrameReplayBuffer.bytes_per_slot
    trainable, other_params = _parameter_counts(cfg, action_dim)
    return RunNeeds(slots=replay_slots(cfg), capacity=cfg.train.replay_capacity,
                    frame_bytes=3 * cfg.env.image_size ** 2, other_bytes=other,  # uint8 RGB
                    agent_bytes=4 * (4 * trainable + other_params), activation_bytes=_activation_bytes(cfg))


def _parameter_counts(cfg: RunConfig, action_dim: int) -> tuple[int, int]:
    """The agent's trainable parameters and its other tensors (target networks, buffers), counted
    on an agent built on the CPU without its initialisation (:func:`shapes_only`); the random
    draws of its building are undone when the training seeds or restores every generator."""
    from imssr.training.build import build_agent

    e = cfg.env
    with shapes_only():
        agent = build_agent(cfg, (3 * e.frame_stack, e.image_size, e.image_size), action_dim, "cpu")
    tensors = {id(t): t for m in (agent.nets, agent.aux, agent.signal) if m is not None
               for t in (*m.parameters(), *m.buffers())}
    trainable = sum(t.numel() for t in tensors.values() if t.requires_grad)
    return trainable, sum(t.numel() for t in tensors.values()) - trainable


def _activation_bytes(cfg: RunConfig) -> int:
    """One update's encoder feature maps kept for the backward pass: each convolution's output and
    its ReLU's, float32, for the RL batch and the auxiliary batch (an estimate: the heads' and
    the auxiliary task's own layers are small beside them)."""
    a = cfg.agent
    maps = sum(conv_output_size(a.crop_size, k) ** 2 for k in range(1, a.encoder_layers + 1))
    per_sample = 2 * 4 * a.encoder_filters * maps
    return per_sample * (a.batch_size + cfg.aux.batch_size)


@dataclass(frozen=True)
class MemoryPlan:
    """What the runs of a training need and where their frames go."""

    needs: RunNeeds
    """One run's (the runs of a batch share their sizes)."""
    device: torch.device
    """The runs' torch device (``train.device``)."""
    placement: ReplayPlacement
    """Where every run's frames go."""


def memory_plan(cfgs: Sequence[RunConfig], runs: Sequence[RunDir]) -> MemoryPlan:
    """Check that the runs ``cfgs`` (in ``runs``, trained in one process) fit this machine's
    memory and disk, and decide where their replay frames go (see the module's doc); a one-line
    error with the arithmetic and the ways out when they do not fit.  Nothing is written."""
    from imssr.training.build import resolve_device

    cfg = cfgs[0]
    needs = max((run_needs(c) for c in {c.algo: c for c in cfgs}.values()), key=lambda n: n.agent_bytes)
    n, device = len(cfgs), resolve_device(cfg.train.device)
    placement = replay_placement(cfg.train.replay_device, device, n * needs.capacity * needs.frame_bytes,
                                 cfg.train.gpu_share, margin_nbytes=auto_margin(needs, n))
    on_gpu = device.type == "cuda"
    frames_in_ram = placement.device.type == "cpu" and not placement.disk
    agents = n * (needs.agent_bytes + needs.activation_bytes)
    _check_host(needs, n, frames_in_ram, 0 if on_gpu else agents, placement.disk)
    if on_gpu:
        _check_gpu(needs, n, placement.device.type == "cuda", agents, device, cfg.train.gpu_share)
    if placement.disk:
        _check_disk(needs, runs)
    return MemoryPlan(needs, device, placement)


def auto_margin(needs: RunNeeds, n: int) -> int:
    """The GPU memory ``auto`` keeps free beside the frames of ``n`` runs of ``needs``: the margin
    of a run alone (:data:`REPLAY_DEVICE_MARGIN_BYTES`, which holds its agent) and the agents of
    the other members of a batch, each with its update's activations (a batch updates them at once)."""
    return REPLAY_DEVICE_MARGIN_BYTES + (n - 1) * (needs.agent_bytes + needs.activation_bytes)


def _runs(n: int) -> str:
    return "this run needs" if n == 1 else f"{n:,} runs need"


def _check_host(needs: RunNeeds, n: int, frames: bool, agents: int, disk: bool) -> None:
    """Host memory: the replay (frames when they live there), the agents on the CPU and the rest
    of the runs (:data:`RUN_HOST_BYTES` each: environments, renderers), against what is available,
    and the replay and agents against what an address-space limit leaves."""
    runs = n * RUN_HOST_BYTES
    per_slot = (needs.frame_bytes if frames else 0) + needs.other_bytes
    replay = n * needs.slots * per_slot
    also = f" and {agents / GB:.1f} GB for agents" if agents else ""
    what = (f"{replay / GB:.1f} GB of host memory for replay ({needs.slots:,} slots x {per_slot:,} B each){also}"
            f" and {runs / GB:.1f} GB for {'its' if n == 1 else 'their'} environments and renderers "
            f"({RUN_HOST_BYTES / 1e6:,.0f} MB a run)")
    ways = "train fewer seeds at once" if n > 1 else "train with a smaller replay"
    ways += ", lower train.replay_capacity" + ("" if disk or not frames else
                                                ", or put the frames on disk with --set train.replay_device=disk")
    available = available_memory_bytes()
    if available is not None and replay + agents + runs > available:
        raise ImssrError(f"{_runs(n)} {what}; {available / GB:.1f} GB is available: {ways}")
    limit, used = address_space_limit(), address_space_in_use()
    if limit is not None and used is not None:
        # The arrays (and a frames file) are mapped at their capacity as the buffer is made.
        mapped = n * needs.capacity * (needs.frame_bytes + needs.other_bytes if frames or disk else needs.other_bytes)
        if mapped + agents > limit - used:
            fewer = "train fewer seeds at once, " if n > 1 else ""
            raise ImssrError(f"{_runs(n)} {mapped / GB:.1f} GB of address space for replay ({needs.capacity:,} "
                             f"slots each){also}; {max(limit - used, 0) / GB:.1f} GB is left: {raise_limit_text()}, "
                             f"or {fewer}lower train.replay_capacity")


def _check_gpu(needs: RunNeeds, n: int, frames: bool, agents: int, device: torch.device, share: float) -> None:
    """GPU memory: the frames when they live there (mapped at their capacity) and the agents,
    against the room :func:`choose_replay_device` counts."""
    if device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    free, total = torch.cuda.mem_get_info(device)
    room = min(free, int(share * total)) if share < 1 else free
    replay = n * needs.capacity * needs.frame_bytes if frames else 0
    if replay + agents <= room:
        return
    what = (f"{replay / GB:.1f} GB of GPU memory for replay frames ({needs.capacity:,} slots x "
            f"{needs.frame_bytes:,} B each) and " if frames else "") + f"{agents / GB:.1f} GB for agents"
    ways = "train fewer seeds at once" + (", or keep the frames in host memory (--set train.replay_device=cpu)"
                                          if frames else ", or lower --batch-size")
    raise ImssrError(f"{_runs(n)} {what}; {room / GB:.1f} GB is free on {device}: {ways}")


def _check_disk(needs: RunNeeds, runs: Sequence[RunDir]) -> None:
    """Local disk: each run's frames file (:meth:`RunDir.frames_file`) against the free space of
    its file system, the runs on one file system together."""
    by_fs: dict[int, list[str]] = {}
    for run in runs:
        where = _existing(run.path)
        by_fs.setdefault(os.stat(where).st_dev, []).append(where)
    for wheres in by_fs.values():
        where, count = wheres[0], len(wheres)
        st = os.statvfs(where)
        free = st.f_bavail * st.f_frsize
        need = count * needs.frames_bytes
        if need > free:
            raise ImssrError(f"{_runs(count)} {need / GB:.1f} GB of disk for replay frames ({needs.slots:,} slots x "
                             f"{needs.frame_bytes:,} B each); {free / GB:.1f} GB is free on the file system of "
                             f"{where}: free some space, train fewer seeds at once or lower train.replay_capacity")


def _existing(path: str) -> str:
    """``path`` or its nearest existing parent."""
    path = os.path.abspath(path)
    while not os.path.exists(path):
        path = os.path.dirname(path)
    return path
