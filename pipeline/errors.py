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


class WriteError(Exception):
    """A folder the run writes cannot take what it writes: no space left, read-only, not a folder, no permission.

    The message reads ``<folder>: <reason> (<errno name>) while <doing> (at <file>)``; ``errno`` is the OS's code.
    """

    def __init__(self, path: str | Path, reason: str, errno: int | None = None):
        self.path = str(path)
        self.reason = reason
        self.errno = errno
        super().__init__(f"{self.path}: {reason}")

    @classmethod
    def from_os_error(cls, folder: str | Path, exc: OSError, doing: str) -> "WriteError":
        import errno as errno_names

        what = exc.strerror or str(exc)
        code = f" ({errno_names.errorcode[exc.errno]})" if exc.errno in errno_names.errorcode else ""
        target = getattr(exc, "filename2", None) or exc.filename  # a copy's destination, else the file
        at = f" (at {target})" if target else ""
        return cls(folder, f"{what}{code} while {doing}{at}", exc.errno)
