"""``python -m ddp``: the same command line as the ``ddp`` script."""

from ddp.cli import main

raise SystemExit(main())
