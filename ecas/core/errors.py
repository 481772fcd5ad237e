"""The one error type of the data pipeline: it always names the file and what is wrong."""

from pathlib import Path


class DataError(ValueError):
    def __init__(self, path: Path | str, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem
