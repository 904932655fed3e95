"""``python -m collider_cli ...`` is ``collider ...``."""

import sys

from .main import main

sys.exit(main())
