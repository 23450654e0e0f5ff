"""The model-versus-measurement workbench: replay, compare, localize, diagnose, fit, report."""
