"""Experiments: learning curves of a run, sweeps of runs on Ray (grid, runner, sweep) and reports."""
from imssr.experiments.curves import plot_learning_curve

__all__ = ["plot_learning_curve"]
