"""Experiments: turning runs into figures (learning curves; sweeps and reports build on this)."""
from imssr.experiments.curves import plot_learning_curve

__all__ = ["plot_learning_curve"]
