"""The one exception every loader raises for a bad file."""

from __future__ import annotations

from pathlib import Path


class BoneFileError(ValueError):
    """A bone file (or series) that cannot be loaded. The message names the file and says what
    is wrong; nothing is half-loaded when it is raised.

    Attributes:
        path: the file or directory at fault.
        problem: what is wrong with it, without the path.
    """

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")
