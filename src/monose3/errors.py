"""The one exception type users see: a one-line message that names the problem and the fix."""


class Monose3Error(Exception):
    """A user-facing error. The CLI prints ``str(err)`` on one line and exits non-zero."""
