import sys
from pathlib import Path

# Make tests/reference.py and tests/helpers.py importable as top-level modules
sys.path.insert(0, str(Path(__file__).resolve().parent))
