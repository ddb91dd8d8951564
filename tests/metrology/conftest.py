"""Make the independent file generator (``filegen.py`` beside the tests) and the tests' own
profilometer simulators (the ``instruments`` package beside it) importable."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
