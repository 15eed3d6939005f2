"""Errors the command line reports as one line: defined here, without torch, so that a job that never
touches a network (evaluation, scoring, reports) does not pay torch's import (about 1.7 s) just to name
them. The modules that raise them re-export them under their old names."""
from __future__ import annotations


class MissingInputError(KeyError):
    """A method asked for a buffer that was not rendered; names the buffer and the method."""

    def __init__(self, method: str, buffer: str, detail: str = "") -> None:
        self.method, self.buffer = method, buffer
        message = f"method {method!r} needs buffer {buffer!r}, which was not rendered"
        super().__init__(message + (f" ({detail})" if detail else ""))

    def __str__(self) -> str:
        return str(self.args[0])


class CheckpointError(RuntimeError):
    """A checkpoint cannot be used; the message names the file and why."""


class NonFiniteLossError(FloatingPointError):
    """Training produced a NaN/Inf loss; ``step`` (0-based, = batch index) and ``batch`` name where."""

    def __init__(self, message: str, step: int, batch: str) -> None:
        super().__init__(message)
        self.step, self.batch = step, batch
