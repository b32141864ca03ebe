"""``python -m monose3``: the same as the ``monose3`` command (for a checkout run with PYTHONPATH=src)."""

from monose3.cli import main

raise SystemExit(main())
