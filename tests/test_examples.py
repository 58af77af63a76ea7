"""The usage example in each package's docstring runs and gives what it shows (doctest)."""

from __future__ import annotations

import doctest
import importlib

import pytest

PACKAGES = ("messages", "gp_model", "fe_node", "controller_node")


@pytest.mark.parametrize("name", PACKAGES)
def test_the_package_usage_example_runs(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted >= 3 and result.failed == 0, f"{name}: {result}"
