import sys
from pathlib import Path

# Make tests/helpers.py and the tests/oracles package importable as top-level modules from the
# test folders (tests/plugin, tests/grains, ...: no __init__.py, pytest's default import mode)
sys.path.insert(0, str(Path(__file__).resolve().parent))

import pytest  # noqa: E402


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run the tests marked slow (long fits and sweeps)")


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: long test, run with --runslow (not in CI's run)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
