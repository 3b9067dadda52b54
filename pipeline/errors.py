"""Errors that name the input at fault and the reason, so a failed action can be reported plainly."""
from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad input: a file that is corrupt, missing, of the wrong size, black or saturated.

    The message always reads ``<path>: <reason>`` so the user knows which file to look at.
    """

    def __init__(self, path: str | Path | None, reason: str):
        self.path = str(path) if path is not None else None
        self.reason = reason
        super().__init__(f"{self.path}: {reason}" if self.path else reason)


class RawDecodeError(InputError):
    """A raw file that LibRaw cannot read or that is not a usable light-stage camera frame."""


class ConfigError(ValueError):
    """A configuration file or override that does not match the typed config (unknown key, bad type)."""
