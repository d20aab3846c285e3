"""``python -m monotracker.sim.pbr``: see :mod:`.build`."""

import sys

from .build import main

sys.exit(main())
