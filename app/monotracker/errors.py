"""User-facing errors.

Anything the operator can cause (a missing file, a corrupt CT, a camera that is unplugged,
a robot that does not answer) raises :class:`MonoTrackerError` with a one-line message that
says what is wrong and what to do. The CLI prints it as ``error: <message>``; the web app shows
it in the page. Programming errors are not wrapped: they are logged with their traceback to
the log file and reported to the user as a short "internal error" line.
"""


class MonoTrackerError(Exception):
    """An expected failure with a one-line, human-readable message."""


class InputError(MonoTrackerError):
    """Bad user input: a file, folder or parameter that cannot be used as given."""
