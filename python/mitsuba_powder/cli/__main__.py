"""``python -m mitsuba_powder.cli``: the ``mitsuba-powder`` command."""

import sys

from . import main

sys.exit(main())
