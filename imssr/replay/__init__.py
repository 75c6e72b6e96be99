"""Replay storage."""
from imssr.replay.buffer import FrameReplayBuffer, available_memory_bytes

__all__ = ["FrameReplayBuffer", "available_memory_bytes"]
