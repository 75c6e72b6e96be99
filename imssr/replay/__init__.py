"""Replay storage: the numpy host store (in memory, or memory-mapped from a file on disk) and the
tensor store on a device (``train.replay_device``)."""
from imssr.replay.buffer import DiskFrameReplayBuffer, FrameReplayBuffer, ReplayMemoryWarning, available_memory_bytes
from imssr.replay.device import (ReplayPlacement, TensorFrameReplayBuffer, choose_replay_device, make_replay_buffer,
                                 replay_placement)

__all__ = ["DiskFrameReplayBuffer", "FrameReplayBuffer", "ReplayMemoryWarning", "ReplayPlacement",
           "TensorFrameReplayBuffer", "available_memory_bytes", "choose_replay_device", "make_replay_buffer",
           "replay_placement"]
