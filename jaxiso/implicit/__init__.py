"""Arbitrary implicit surfaces (seed ch. 6): the catalogue of test surfaces."""

from . import surfaces

__all__ = ["surfaces"]
