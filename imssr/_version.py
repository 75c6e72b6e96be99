"""imssr's version, in one place (``imssr.__version__``, run provenance records)."""
__version__ = "0.2.0"
