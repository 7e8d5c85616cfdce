"""What acting from an exported policy reports as bad input."""
from __future__ import annotations


class PolicyError(ValueError):
    """A policy directory that cannot be used: a missing or unreadable file, a hash that
    does not match, or a model whose inputs/outputs do not fit the declared algorithm."""
