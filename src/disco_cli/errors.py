"""The errors disco raises for bad input.

Every user-facing failure is a `DiscoError`: the command line prints its message
as one line and exits non-zero, never with a traceback. Messages name the file
and the problem.
"""

from __future__ import annotations

from pathlib import Path


class DiscoError(Exception):
    """Base of every error caused by the user's input or environment."""


class ScanReadError(DiscoError):
    """A scan file could not be read: missing, truncated, misaligned, empty or unparsable."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class DatabaseError(DiscoError):
    """A map database is missing, corrupt, of another format version or another model."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class ModelError(DiscoError):
    """A model checkpoint is missing, unreadable or of an unknown layout."""


class PoseFileError(DiscoError):
    """A poses, times or calibration file is missing or malformed."""
