"""The project's exceptions: every user-facing error derives from :class:`BoxlocError`."""

from __future__ import annotations


class BoxlocError(Exception):
    """Base of all boxloc errors. The CLI prints ``str(err)`` on one line and exits 2."""


class InputError(BoxlocError, ValueError):
    """A scan, file or parameter given by the user is unusable."""


class LogError(BoxlocError):
    """A recorded log is corrupt, truncated, of an unknown schema, or otherwise unreadable."""
