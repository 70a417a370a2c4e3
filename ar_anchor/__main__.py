"""``python -m ar_anchor`` is ``ar-anchor``."""

import sys

from .cli.main import main

sys.exit(main())
