"""Inverse transform: frames -> shape coefficients (d, p, a, b) and centre displacement D(0, t)."""
from service.inverse.base import InverseMethod, InverseOutput

__all__ = ["InverseMethod", "InverseOutput"]
