"""``python -m services.evaluator``: the evaluator service (see services/evaluator/service.py)."""

import sys

from services.evaluator.service import main

sys.exit(main())
