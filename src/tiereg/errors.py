"""The exceptions tiereg raises.

Every error tiereg raises on purpose derives from :class:`TieregError`. Messages are one line that
says what is wrong *and what to do*; the command line prints them as they are (exit code 2).
"""

from __future__ import annotations


class TieregError(Exception):
    """Root of all tiereg errors."""


class InputError(TieregError, ValueError):
    """An input (file, array or option) cannot be used as given."""


class FormatError(InputError):
    """A file is not in a format tiereg reads, or it is corrupt or truncated."""


class OutputError(TieregError, OSError):
    """An output file cannot be written."""


class MissingDependencyError(TieregError, ImportError):
    """An optional package needed for this feature is not installed."""
