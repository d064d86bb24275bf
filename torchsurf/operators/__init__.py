"""Intrinsic differential operators on implicit surfaces: functions and their modules."""

from .laplace_beltrami import LaplaceBeltrami, laplace_beltrami

__all__ = ["LaplaceBeltrami", "laplace_beltrami"]
