"""The solver's own errors; each says what happened and with which numbers."""
from __future__ import annotations


class SolverError(RuntimeError):
    """Base of every error the solver raises on purpose."""


class Unstable(SolverError):
    """The state has blown up mid-frame; the message says how, and `where` (m), if known, is
    the fastest particle's position then."""

    def __init__(self, message: str, where: tuple[float, float, float] | None = None):
        super().__init__(message)
        self.where = where


class TooLarge(SolverError):
    """The particles or their neighbour lists would not fit (the message gives the counts)."""


class NoParticles(SolverError):
    """The fluid blocks hold no particle once the colliders are cut out of them."""
