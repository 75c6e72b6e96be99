"""Intrinsic rewards: the raw signal of o' (IM-SSR's SSL loss, RND, RE3), then
in-batch normalisation and the beta schedule (:class:`IntrinsicReward`); the signals by name in
:mod:`~imssr.intrinsic.registry`."""
from imssr.intrinsic.base import FORMS, IntrinsicSignal, SSLSignal
from imssr.intrinsic.re3 import RE3
from imssr.intrinsic.registry import INTRINSIC_SIGNALS, make_signal
from imssr.intrinsic.reward import NORMALIZATIONS, SCHEDULES, BetaSchedule, IntrinsicReward, normalize
from imssr.intrinsic.rnd import RND

__all__ = ["BetaSchedule", "IntrinsicReward", "IntrinsicSignal", "SSLSignal", "RND", "RE3", "INTRINSIC_SIGNALS",
           "FORMS", "NORMALIZATIONS", "SCHEDULES", "make_signal", "normalize"]
