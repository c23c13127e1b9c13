"""The one exception type for bad user input: it always names the offending file and the problem."""
from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """Bad input data. The message names the file (when there is one) and what is wrong with it.

    The CLI prints these without a traceback; library users can catch them to skip one bad item.
    """

    def __init__(self, problem: str, path: str | Path | None = None, hint: str | None = None):
        self.path = None if path is None else Path(path)
        self.problem = problem
        self.hint = hint
        msg = f"{path}: {problem}" if path is not None else problem
        if hint:
            msg += f" ({hint})"
        super().__init__(msg)
