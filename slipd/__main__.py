"""``python -m slipd``: the same as the ``slipd`` command."""

from slipd.cli import main

raise SystemExit(main())
