"""One exception type for bad user input, so the CLI and nodes can report it cleanly."""

from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """Bad input data; the message names the file, topic or field and the problem."""

    def __init__(self, where: str | Path, problem: str) -> None:
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{self.where}: {problem}")


__all__ = [
    "InputError",
]
