"""One exception type for bad user input, so the CLI and nodes can report it cleanly, and the once-per-source warning
for input that is taken but worth saying about.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any


class InputError(ValueError):
    """Bad input data; the message names the file, topic or field and the problem."""

    def __init__(self, where: str | Path, problem: str) -> None:
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{self.where}: {problem}")


_MAX_WARNED = 1024
_warned: set[tuple[str, str]] = set()
"""The (source, what) pairs said so far by :func:`warn_once`."""


def warn_once(log: logging.Logger, source: str, what: str, msg: str, *args: Any) -> None:
    """``log.warning(msg, *args)`` the first time ``(source, what)`` comes: a file or topic that repeats the same thing
    in every line or message says it once. Bounded: beyond :data:`_MAX_WARNED` pairs, warnings repeat rather than grow.
    """
    key = (source, what)
    if key in _warned:
        return
    if len(_warned) < _MAX_WARNED:
        _warned.add(key)
    log.warning(msg, *args)


__all__ = [
    "InputError",
    "warn_once",
]
