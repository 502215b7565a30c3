"""``python -m services.router``: see :mod:`services.router`."""

import sys

from services.router import main

sys.exit(main())
