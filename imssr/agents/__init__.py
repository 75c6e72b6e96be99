"""Agents: pixel SAC with pluggable auxiliary task and intrinsic reward."""
from imssr.agents.build import make_agent
from imssr.agents.sac import SACAgent, SACNetworks

__all__ = ["SACAgent", "SACNetworks", "make_agent"]
