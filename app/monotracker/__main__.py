"""``python -m monotracker`` is the same as the ``monotracker`` console script."""

from monotracker.cli import main

raise SystemExit(main())
