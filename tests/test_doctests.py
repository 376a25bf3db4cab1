"""The runnable examples in the docstrings of every module of ``cylsfm`` run with the tests.

The package is walked when the tests are collected, so a module added or moved is picked up without a list to keep:
a wrong example anywhere in ``src/cylsfm`` fails here (``pytest tests`` alone runs them, whatever ``testpaths`` say).
"""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import cylsfm

# pytest's own doctest default; the examples were written against it.
FLAGS = doctest.ELLIPSIS


def _unimportable(name: str) -> None:
    raise ImportError(f"{name} does not import, so its doctests cannot be collected")  # not skipped silently


def _module_names() -> list[str]:
    names = [cylsfm.__name__]
    for info in pkgutil.walk_packages(cylsfm.__path__, prefix=f"{cylsfm.__name__}.", onerror=_unimportable):
        if info.name.rsplit(".", 1)[-1] != "__main__":  # running it is the command line, not a module to read
            names.append(info.name)
    return sorted(names)


MODULES = _module_names()


def _run(name: str) -> doctest.TestResults:
    module = importlib.import_module(name)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    report: list[str] = []
    for test in doctest.DocTestFinder().find(module, name):
        runner.run(test, out=report.append)
    results = doctest.TestResults(runner.failures, runner.tries)
    assert results.failed == 0, (
        f"{name}: {results.failed} of {results.attempted} examples failed\n" + "".join(report)
    )
    return results


@pytest.mark.parametrize("name", MODULES)
def test_module_doctests(name):
    _run(name)


def test_walk_finds_every_module_with_examples():
    """The walk reaches the modules whose examples were never run before, and their examples are found."""
    for name in ("cylsfm.data.stitch", "cylsfm.evaluate.motion", "cylsfm.evaluate.tables", "cylsfm.errors"):
        assert name in MODULES
        assert _run(name).attempted > 0, name
    assert "cylsfm.geometry.cameras" in MODULES and "cylsfm.cli.__main__" not in MODULES
