"""Evaluation: the paper's error metrics, Table-I style evaluation, benchmarks and synthetic test data."""

from place_safe.evaluation.metrics import angular_error, linear_error, point_error

__all__ = ["angular_error", "linear_error", "point_error"]
