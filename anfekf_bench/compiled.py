"""numba where it is installed and not switched off: the one switch for compiled code. The fast
engine's kernels (engines.kernels, which adds its plain-Python copy), the simulator's truth loop
and the bootstrap's time means (analysis.run_means) all compile through it.

Set the environment variable ANFEKF_FAST_JIT=0 to keep numba off even when it is installed.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
import threading
from pathlib import Path

# numba's cache keeps one entry per function and signature, whatever the options: one set for
# every compiled function. nogil: the callers run on threads.
NJIT_OPTIONS = {"cache": True, "nogil": True, "error_model": "numpy"}


def numba_njit():
    """numba.njit, or None when numba is missing or switched off (ANFEKF_FAST_JIT=0); its disk
    cache told that this package's functions depend on the sources they reach
    (`use_reached_sources_stamp`)."""
    if os.environ.get("ANFEKF_FAST_JIT", "1") == "0":
        return None
    try:
        import numba
    except ImportError:
        return None
    use_reached_sources_stamp()
    return numba.njit


def maybe_njit(fn):
    """`fn` compiled with `NJIT_OPTIONS` when numba is in use, else the function itself."""
    njit = numba_njit()
    return fn if njit is None else njit(**NJIT_OPTIONS)(fn)


def is_compiled(fn) -> bool:
    """Whether `maybe_njit` compiled `fn` (a numba dispatcher keeps the Python function)."""
    return hasattr(fn, "py_func")


# ---------------------------------------------------------------------------------------------
# numba's disk cache, told what a compiled function depends on

_PACKAGE_ROOT = Path(__file__).resolve().parent


def reached_modules(*roots) -> list:
    """This package's modules whose functions compiled code in `roots` can call: each module's
    globals that are modules or functions of the package (numba dispatchers included), followed
    to the end; in name order."""
    import inspect
    import types

    package = f"{__name__.split('.')[0]}."
    seen: dict = {}
    todo = list(roots)
    while todo:
        mod = todo.pop()
        if mod.__name__ in seen:
            continue
        seen[mod.__name__] = mod
        for value in list(vars(mod).values()):
            if isinstance(value, types.ModuleType):
                name = value.__name__
            elif inspect.isfunction(value) or hasattr(value, "py_func"):
                name = getattr(value, "__module__", None) or ""
            else:
                continue
            if name.startswith(package) and name in sys.modules:
                todo.append(sys.modules[name])
    return [seen[name] for name in sorted(seen)]


@functools.cache
def _file_digest(path: str, mtime_ns: int, size: int) -> bytes:
    """sha256 of a file's bytes (memoised on its path, time and size, as numba's own)."""
    return hashlib.sha256(Path(path).read_bytes()).digest()


# The package's sources' modification times when the stamp was installed (or, for a source
# first seen later, when first seen): a source edited afterwards is not the code this process
# compiles.
_SOURCE_TIMES: dict = {}


def _source_times() -> dict:
    return {
        str(path.resolve()): path.stat().st_mtime_ns
        for path in _PACKAGE_ROOT.rglob("*.py")
        if "__pycache__" not in path.relative_to(_PACKAGE_ROOT).parts
    }


def unchanged_source_stat(path: str) -> os.stat_result | None:
    """os.stat of the source at `path` (resolved), or None where it changed since this process
    first saw it (when the stamp was installed, else at this call): the code this process runs
    is not the edited file's."""
    st = os.stat(path)
    return st if st.st_mtime_ns == _SOURCE_TIMES.setdefault(path, st.st_mtime_ns) else None


def reached_sources_digest(module) -> str:
    """A digest of the sources of every package module `module` reaches (itself included); a
    stamp that no process matches where one of them changed after this process saw it (its
    compiled code would otherwise be cached under the edited sources' stamp). OSError where a
    source cannot be read."""
    digest = hashlib.sha256()
    for reached in reached_modules(module):
        path = getattr(reached, "__file__", None)
        if path:
            path = str(Path(path).resolve())
            st = unchanged_source_stat(path)
            if st is None:
                return f"{path} changed after this process read it ({os.urandom(8).hex()})"
            digest.update(_file_digest(path, st.st_mtime_ns, st.st_size))
    return digest.hexdigest()


_STAMP_LOCK = threading.Lock()
_STAMP_INSTALLED: list = []


def use_reached_sources_stamp() -> None:
    """Make numba's disk cache of this package's functions stale when any source they reach
    changes, not only their own file (numba's stamp): a kernel compiles its callees from other
    files into its cached code (engines/kernels.py's steps, filters/'s rules, the motion model),
    so an edit there, or a `git pull` that changes only them, would otherwise leave the kernel
    running the old code. Functions of other packages, and a NUMBA_CACHE_LOCATOR_CLASSES of the
    user's, are left as numba has them. Once per process, before the package's first compiled
    function is decorated (compiled.numba_njit and the problems' modules call it)."""
    with _STAMP_LOCK:
        if not _STAMP_INSTALLED:
            _SOURCE_TIMES.update(_source_times())
            _install_locator()
            _STAMP_INSTALLED.append(True)


def _install_locator() -> None:
    from numba.core import caching

    # numba's locators (numba.core.caching: `CacheImpl` and `_CacheLocator` in 0.59-0.68); a
    # numba without them keeps its own stamp
    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
    base = getattr(caching, "_CacheLocator", None)
    locators = getattr(impl, "_locator_classes", None)
    if base is None or not isinstance(locators, list):
        return

    class ReachedSourcesLocator(base):
        """numba's own locator for a function of this package (the same cache folder and file
        names; any other attribute numba reads is its too), whose freshness stamp is numba's for
        its file and `reached_sources_digest` of its module, taken when the function is
        decorated."""

        def __init__(self, inner, digest: str):
            self._inner = inner
            self._stamp = (inner.get_source_stamp(), digest)

        def __getattr__(self, name):  # e.g. _py_file, read where numba cannot cache a function
            inner = self.__dict__.get("_inner")
            if inner is None:  # (not built through __init__: a copy being made)
                raise AttributeError(name)
            return getattr(inner, name)

        def ensure_cache_path(self):
            return self._inner.ensure_cache_path()

        def get_cache_path(self):
            return self._inner.get_cache_path()

        def get_disambiguator(self):
            return self._inner.get_disambiguator()

        def get_source_stamp(self):
            return self._stamp

        @classmethod
        def from_function(cls, py_func, py_file):
            module = sys.modules.get(getattr(py_func, "__module__", None) or "")
            try:
                inside = Path(py_file).resolve().is_relative_to(_PACKAGE_ROOT)
            except (OSError, ValueError):
                inside = False
            if module is None or not inside:
                return None
            for other in locators:
                if other is not cls:
                    inner = other.from_function(py_func, py_file)
                    if inner is not None:
                        try:
                            return cls(inner, reached_sources_digest(module))
                        except OSError:  # a source that cannot be read (a zipped install)
                            return inner
            return None

    locators.insert(0, ReachedSourcesLocator)
