"""``python -m ar_anchor`` is ``ar-anchor``."""

import sys

from .cli import main

sys.exit(main())
