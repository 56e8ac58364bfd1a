"""Stopping long scoring work between its units (a candidate, a training view, a keyframe render) when asked: a node
shutting down must not wait for a whole scoring call, and must not keep half of one.
"""

from __future__ import annotations

from collections.abc import Callable

ShouldStop = Callable[[], bool] | None
"""A check scoring calls between its units of work (a candidate, a training view); True stops it."""


class ScoringStoppedError(RuntimeError):
    """Raised by scoring when its ``should_stop`` turned true (a node shutting down): no result, nothing half-kept."""


def check_stop(should_stop: ShouldStop) -> None:
    """Raise :class:`ScoringStoppedError` if ``should_stop`` says so."""
    if should_stop is not None and should_stop():
        raise ScoringStoppedError("scoring stopped: asked to stop (shutting down)")


__all__ = ["ScoringStoppedError", "ShouldStop", "check_stop"]
