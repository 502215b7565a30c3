"""``python -m services.router``: see :mod:`services.router.service`."""

import sys

from services.router.service import main

sys.exit(main())
