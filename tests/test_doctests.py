"""The examples in the library's docstrings (``>>>`` lines) run as written and print what they say."""
import doctest
import importlib
import pkgutil

import pytest

import ams_torch

#: modules whose examples this suite must find (so a docstring rewritten without them is noticed)
MUST_HAVE_EXAMPLES = ("ams_torch.sim.simulator", "ams_torch.sim.builder")


def _modules():
    for info in pkgutil.walk_packages(ams_torch.__path__, "ams_torch."):
        if info.name.endswith("__main__"):  # importing it runs the CLI
            continue
        try:
            yield importlib.import_module(info.name)
        except ImportError:  # an optional dependency (e.g. a renderer) is missing here
            continue


def _examples():
    finder = doctest.DocTestFinder(exclude_empty=True)
    out = []
    for module in _modules():
        for test in finder.find(module, module.__name__):
            if test.examples and test.name.startswith(module.__name__):
                out.append(test)
    return out


EXAMPLES = _examples()


def test_the_public_docstrings_have_examples():
    found = {m for m in MUST_HAVE_EXAMPLES if any(t.name.startswith(m) for t in EXAMPLES)}
    assert found == set(MUST_HAVE_EXAMPLES), sorted(t.name for t in EXAMPLES)


@pytest.mark.parametrize("test", EXAMPLES, ids=lambda t: t.name)
def test_docstring_example(test):
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{test.name}: {result.failed} of {result.attempted} examples failed (output above)"
