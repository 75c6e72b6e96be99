"""Replay storage."""
from imssr.replay.buffer import FrameReplayBuffer, ReplayMemoryWarning, available_memory_bytes

__all__ = ["FrameReplayBuffer", "ReplayMemoryWarning", "available_memory_bytes"]
