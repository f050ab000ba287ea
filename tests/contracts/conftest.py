"""Contract tests: every registered entry goes through the same checks (tests/contracts/)."""

import sys
from pathlib import Path

# the shared naive references live in tests/references.py
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
