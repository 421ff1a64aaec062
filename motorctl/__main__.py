"""``python -m motorctl``: the same program as the ``motorctl`` console script."""

import sys

from motorctl.cli import main

sys.exit(main())
