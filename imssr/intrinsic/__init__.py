"""Intrinsic rewards (IM-SSR): normalisation and beta schedule."""
from imssr.intrinsic.reward import BetaSchedule, IntrinsicReward, normalize

__all__ = ["BetaSchedule", "IntrinsicReward", "normalize"]
