"""Shared helpers (testbed.py) for the scenario test directories below."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
