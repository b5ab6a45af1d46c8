"""numba's on-disk cache, made safe against edits of the files a kernel calls into.

numba stamps a cached kernel with the hash of its *own* source file only.  A kernel
compiled together with functions from other files (``sim/dem.py``'s stepper inlines
the laws of ``sim/forces/*.py``; ``ptrack/image/locate``'s kernels call ``fit``) keeps
running the old callees from the cache after those files change: a developer's edit,
or an upgrade that leaves the caller's file as it was, silently runs old code (and
times it).  This module registers cache locators, used for this project's files only,
whose stamp is the hash of the kernel's file together with the hashes of every project
module that file imports, directly or through others.  An edit then recompiles exactly
the kernels that can contain the edited code; unrelated kernels stay cached.

``ptrack/__init__.py`` (and so ``sim/__init__.py``, which imports it) calls :func:`install`,
which registers the locators when numba's caching module is first imported (so ``import
ptrack`` stays free of numba's start-up time), before any kernel is defined.  Dependencies
are read from a module's namespace when its kernels are decorated: a project import placed
below a cached kernel in its file is not seen by that kernel's stamp (keep imports at the top).
Needs no configuration; if numba's (private) locator API is not the one expected, the
registration is skipped and numba's own per-file stamps apply.
"""

from __future__ import annotations

import hashlib
import importlib.abc
import importlib.machinery
import os
import sys
import types

_HERE = os.path.dirname(os.path.abspath(__file__))
# package directories whose modules count as this project's (tests add temporary packages)
PROJECT_ROOTS: list[str] = [_HERE, os.path.join(os.path.dirname(_HERE), "sim")]


def _is_project_module(name: str) -> bool:
    mod = sys.modules.get(name)
    path = getattr(mod, "__file__", None)
    if not path:
        return False
    path = os.path.abspath(path)
    return any(path.startswith(os.path.join(root, "")) for root in PROJECT_ROOTS)


def _file_digest(path: str) -> bytes:
    st = os.stat(path)
    return _digest_cached(path, st.st_mtime_ns, st.st_size)


_DIGESTS: dict[tuple, bytes] = {}


def _digest_cached(path: str, mtime_ns: int, size: int) -> bytes:
    # keyed by mtime and size as numba does, so a file edited while the process runs is hashed again
    key = (path, mtime_ns, size)
    d = _DIGESTS.get(key)
    if d is None:
        with open(path, "rb") as f:
            d = hashlib.sha256(f.read()).digest()
        _DIGESTS[key] = d
    return d


def _direct_imports(mod: types.ModuleType) -> set[str]:
    """Names of the project modules that ``mod``'s namespace refers to: imported modules, and the
    modules that imported functions, numba dispatchers and classes were defined in."""
    out = set()
    for value in list(vars(mod).values()):
        if isinstance(value, types.ModuleType):
            name = value.__name__
        else:
            py_func = getattr(value, "py_func", None)  # a numba dispatcher
            name = getattr(py_func if py_func is not None else value, "__module__", None)
        if isinstance(name, str) and name != mod.__name__ and _is_project_module(name):
            out.add(name)
    return out


def dependency_files(module_name: str) -> list[str]:
    """Source files of ``module_name`` and of every project module it imports, directly or through
    others (sorted, ``module_name``'s own file first).

    Read from the modules' namespaces at the time of the call: when a kernel is decorated, the
    imports at the top of its file have run.
    """
    seen = {module_name}
    todo = [module_name]
    while todo:
        mod = sys.modules.get(todo.pop())
        if mod is None:
            continue
        for name in _direct_imports(mod):
            if name not in seen:
                seen.add(name)
                todo.append(name)
    own = os.path.abspath(sys.modules[module_name].__file__)
    files = {os.path.abspath(sys.modules[n].__file__) for n in seen if getattr(sys.modules.get(n), "__file__", None)}
    files.discard(own)
    return [own] + sorted(files)


def source_stamp(module_name: str) -> bytes:
    """sha256 over the contents of :func:`dependency_files` (the stamp of a cached kernel)."""
    h = hashlib.sha256()
    for path in dependency_files(module_name):
        h.update(path.encode())
        h.update(_file_digest(path))
    return h.digest()


class _DependencyStampMixin:
    """A locator stamp that changes when the kernel's file or any project file it imports changes."""

    @classmethod
    def from_function(cls, py_func, py_file):
        name = getattr(py_func, "__module__", None)
        if not name or name not in sys.modules or not _is_project_module(name):
            return None  # not ours: numba's own locators take it
        if os.path.abspath(sys.modules[name].__file__) != os.path.abspath(py_file):
            return None
        self = super().from_function(py_func, py_file)
        if self is not None:
            self._ptrack_module = name
        return self

    def get_source_stamp(self):
        return source_stamp(self._ptrack_module)


def _register(caching=None) -> bool:
    """Put the dependency-stamp locators in front of numba's own; True if they are in place."""
    if caching is None:
        try:
            from numba.core import caching
        except ImportError:  # pragma: no cover - numba is a hard dependency
            return False
    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
    bases = []
    for names in (("UserProvidedCacheLocator", "_UserProvidedCacheLocator"),
                  ("InTreeCacheLocator", "_InTreeCacheLocator"),
                  ("UserWideCacheLocator", "_UserWideCacheLocator")):
        base = next((getattr(caching, n) for n in names if hasattr(caching, n)), None)
        if base is None:
            return False
        bases.append(base)
    if impl is None or not isinstance(getattr(impl, "_locator_classes", None), list):
        return False
    if any(getattr(c, "_ptrack_dependency_stamp", False) for c in impl._locator_classes):
        return True
    ours = [type("Project" + b.__name__.lstrip("_"), (_DependencyStampMixin, b), {"_ptrack_dependency_stamp": True})
            for b in bases]
    impl._locator_classes[:0] = ours
    return True


_CACHING = "numba.core.caching"


class _RegisterAfterImport(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """One-shot import hook: lets numba's caching module load as usual, then registers."""

    def find_spec(self, name, path, target=None):
        if name != _CACHING:
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None:
            return spec
        self._loader = spec.loader
        spec.loader = self
        return spec

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module):
        self._loader.exec_module(module)
        _register(module)


def install() -> None:
    """Register now if numba's caching module is loaded, else as soon as it is."""
    if _CACHING in sys.modules:
        _register(sys.modules[_CACHING])
    elif not any(isinstance(f, _RegisterAfterImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _RegisterAfterImport())


def registered() -> bool:
    """True when this project's kernels are cached under the dependency stamp."""
    from numba.core import caching

    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
    return any(getattr(c, "_ptrack_dependency_stamp", False) for c in getattr(impl, "_locator_classes", ()))
