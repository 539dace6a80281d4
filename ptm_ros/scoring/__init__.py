"""Scoring against ground truth: the topology and calibration scores of ``ptm-eval`` and the reference
methods a user might run instead (baselines)."""
