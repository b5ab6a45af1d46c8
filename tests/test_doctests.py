"""The examples in the docstrings of the analysis entry points run as written (scikit-image style)."""
import doctest
import importlib

import pytest

MODULES = ["ptrack.motion", "ptrack.motion.diffusion", "ptrack.motion.tracks", "ptrack.motion.truth", "ptrack.motion.stokes", "ptrack.analysis",
           "ptrack.plot", "ptrack.mainjob", "ptrack.twin", "ptrack.image.locate"]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.attempted > 0, f"{name} has no example"
    assert res.failed == 0
