"""ar_anchor: real-time fiducial-marker AR tracking."""
from __future__ import annotations

__version__ = "0.1.0"
