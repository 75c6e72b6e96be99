"""Agents: pixel SAC with pluggable auxiliary task and intrinsic reward."""
from imssr.agents.sac import SACAgent, SACNetworks

__all__ = ["SACAgent", "SACNetworks"]
