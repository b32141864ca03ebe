"""The one exception type users see: a one-line message that names the problem and the fix."""

from __future__ import annotations

import sys
from collections.abc import Callable


class Monose3Error(Exception):
    """A user-facing error. The CLI prints ``str(err)`` on one line and exits non-zero."""


def run_reporting_errors(run: Callable[[], int | None], name: str) -> int:
    """Exit code of ``run()``; a Monose3Error or Ctrl-C becomes one line on stderr (2 / 130)
    instead of a traceback. Serves the ``monose3`` commands and the benchmark scripts."""
    try:
        return int(run() or 0)
    except Monose3Error as err:
        print(f"{name}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return 130
