"""adadex: modulated dexterous-manipulation tracking on MuJoCo, and a model-vs-measurement workbench."""

from adadex.errors import AdadexError

__version__ = "0.1.0"
__all__ = ["AdadexError", "__version__"]
