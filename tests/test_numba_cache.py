"""The numba cache stamp covers the files a kernel imports (ptrack/_numba_cache.py).

Each case runs fresh Python processes on a small temporary package: ``callee.py`` holds a
non-cached njit function, ``caller.py`` a cached kernel that calls it, ``other.py`` an unrelated
cached kernel.  numba alone stamps ``caller``'s cache with ``caller.py`` only, so after an edit of
``callee.py`` the second process would still print the old value.
"""

import os
import subprocess
import sys
import textwrap

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

DRIVER = textwrap.dedent("""
    import json, os, sys
    sys.path.insert(0, {tmp!r})
    import ptrack._numba_cache as nc
    if os.environ.get("PROBE_PLAIN") != "1":
        nc.PROJECT_ROOTS.append(os.path.join({tmp!r}, "probe"))
    from probe import caller, other
    out = {{"caller": caller.kernel(), "other": other.kernel(),
           "caller_hits": sum(caller.kernel.stats.cache_hits.values()),
           "other_hits": sum(other.kernel.stats.cache_hits.values())}}
    print(json.dumps(out))
""")


def _write(path, text):
    with open(path, "w") as f:
        f.write(textwrap.dedent(text))


def _package(tmp, value):
    pkg = os.path.join(tmp, "probe")
    os.makedirs(pkg, exist_ok=True)
    _write(os.path.join(pkg, "__init__.py"), "")
    _write(os.path.join(pkg, "callee.py"), f"""
        from numba import njit

        @njit
        def value():
            return {value}
    """)
    _write(os.path.join(pkg, "caller.py"), """
        from numba import njit
        from probe.callee import value

        @njit(cache=True)
        def kernel():
            return value() + 0.5
    """)
    _write(os.path.join(pkg, "other.py"), """
        from numba import njit

        @njit(cache=True)
        def kernel():
            return 7.0
    """)


def _run(tmp, plain=False):
    import json

    env = dict(os.environ, PYTHONPATH=ROOT)
    env.pop("NUMBA_CACHE_DIR", None)  # the in-tree cache of the temporary package
    if plain:
        env["PROBE_PLAIN"] = "1"
    script = DRIVER.format(tmp=str(tmp))
    res = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_registered():
    import numba  # noqa: F401

    import ptrack._numba_cache as nc

    assert nc.registered()


def test_callee_edit_recompiles_caller_only(tmp_path):
    _package(tmp_path, 1)
    first = _run(tmp_path)
    assert first["caller"] == 1.5 and first["other"] == 7.0
    again = _run(tmp_path)
    assert again["caller_hits"] == 1 and again["other_hits"] == 1  # both loaded from the cache
    _write(os.path.join(tmp_path, "probe", "callee.py"), """
        from numba import njit

        @njit
        def value():
            return 2
    """)
    edited = _run(tmp_path)
    assert edited["caller"] == 2.5  # the edit reached the cached caller
    assert edited["caller_hits"] == 0
    assert edited["other_hits"] == 1  # an unrelated kernel stays cached


def test_plain_numba_keeps_the_stale_callee(tmp_path):
    """The trap itself, so that the test above is known to test something: without the
    dependency stamp the cached caller keeps the old callee."""
    _package(tmp_path, 1)
    assert _run(tmp_path, plain=True)["caller"] == 1.5
    _write(os.path.join(tmp_path, "probe", "callee.py"), """
        from numba import njit

        @njit
        def value():
            return 2
    """)
    stale = _run(tmp_path, plain=True)
    if stale["caller"] != 1.5:
        pytest.skip("this numba version re-checks callees itself")
    assert stale["caller_hits"] == 1


def test_project_kernels_use_the_dependency_stamp():
    import ptrack._numba_cache as nc
    import sim.dem

    files = nc.dependency_files("sim.dem")
    assert files[0].endswith(os.path.join("sim", "dem.py"))
    assert any(f.endswith(os.path.join("sim", "forces", "contact.py")) for f in files)
    locator = sim.dem._end_step._cache._impl.locator
    assert getattr(type(locator), "_ptrack_dependency_stamp", False)
    assert locator.get_source_stamp() == nc.source_stamp("sim.dem")
