"""adadex: modulated dexterous-manipulation tracking on MuJoCo, and a model-vs-measurement workbench."""

__version__ = "0.1.0"
