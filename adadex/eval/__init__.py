"""Evaluation: the paper's metrics, tables and loops."""
