"""``python -m monose3``: the same as the ``monose3`` command."""

import sys

from monose3.apps.cli import main

sys.exit(main())
