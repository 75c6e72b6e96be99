"""``imssr analyze``: the paper's Section III terms measured on the states of a trained run
(:mod:`~imssr.analysis.analyze`; docs/analysis.md)."""
from imssr.analysis.adapter import intrinsic_signal
from imssr.analysis.analyze import DEFAULT_MODES, AnalysisOptions, AnalysisResult, analyze_run
from imssr.analysis.states import SOURCES

__all__ = ["AnalysisOptions", "AnalysisResult", "analyze_run", "intrinsic_signal", "SOURCES", "DEFAULT_MODES"]
