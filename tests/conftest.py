"""Shared pytest configuration: make tests/meshes.py importable as ``meshes``."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
