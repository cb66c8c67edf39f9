"""``python -m burrforce.server.cli``: the ``burrforce`` command."""

import sys

from . import main

sys.exit(main())
