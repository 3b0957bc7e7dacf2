"""The one exception a user's broken dataset raises: it names the file and what is wrong with it."""

from __future__ import annotations

from pathlib import Path

from model.errors import InvalidInput


class SceneError(InvalidInput):
    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    # crosses process boundaries whole (the service decodes uploads in worker processes)
    def __reduce__(self):
        return type(self), (self.path, self.problem)
