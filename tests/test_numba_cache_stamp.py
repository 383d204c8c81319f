"""numba's disk cache of this package's functions goes stale when a source they reach changes,
not only their own file (compiled.use_reached_sources_stamp): a kernel compiles its callees from
other files into its cached code, and a `git pull` that changes only a callee's file must not
leave the kernel running the old code."""

from __future__ import annotations

import importlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import anfekf_bench
from anfekf_bench import compiled
from anfekf_bench.sources import simulator

pytestmark = pytest.mark.slow

# The simulator's truth loop (`simulator._drive`, cached) steps the pose with
# models/motion_terms.step_terms, another file: the route it drives, and what numba's cache did.
_DRIVE = """
import json
import numpy as np
from anfekf_bench.sources.simulator import _drive

xs, us = np.empty((201, 3)), np.empty((200, 2))
state = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])  # x, y, phi, gamma, waypoint, loops left
params = (0.025, 3.0, 4.0, 1.0, 0.35 * 0.025, 0.5)  # T, V, B, tolerance^2, max delta, max steer
n, _ = _drive(np.array([[20.0, 20.0]]), state, params, xs, us)
print(json.dumps(xs[n].tolist()))
"""

_HEADING_STEP = "(dt * u0 * math.sin(u1) / B),"


def _drive(package_parent: Path, cache: Path) -> tuple[list, str]:
    env = dict(
        os.environ, NUMBA_CACHE_DIR=str(cache), NUMBA_DEBUG_CACHE="1",
        PYTHONPATH=str(package_parent), ANFEKF_FAST_JIT="1",
    )  # fmt: skip
    proc = subprocess.run(
        [sys.executable, "-c", _DRIVE], env=env, capture_output=True, text=True, check=True,
        cwd=package_parent,
    )  # fmt: skip
    lines = proc.stdout.strip().splitlines()
    return json.loads(lines[-1]), "\n".join(lines[:-1])


def test_an_edited_callee_file_compiles_the_caller_anew(tmp_path) -> None:
    pytest.importorskip("numba")
    copy = tmp_path / "src"
    shutil.copytree(
        Path(anfekf_bench.__file__).parent, copy / "anfekf_bench",
        ignore=shutil.ignore_patterns("__pycache__", "data"),
    )  # fmt: skip
    cache = tmp_path / "cache"
    first, log = _drive(copy, cache)
    assert "data saved" in log and "simulator._drive" in log
    again, log = _drive(copy, cache)
    assert again == first
    assert "simulator._drive" in log and "data saved" not in log, "loaded from the cache"
    motion_terms = copy / "anfekf_bench" / "models" / "motion_terms.py"
    text = motion_terms.read_text()
    assert text.count(_HEADING_STEP) == 1
    motion_terms.write_text(text.replace(_HEADING_STEP, "(2.0 * dt * u0 * math.sin(u1) / B),"))
    edited, log = _drive(copy, cache)  # simulator.py itself unchanged
    assert "data saved" in log, "the caller compiled anew"
    assert edited != first, "the edited step runs, not the cached old one"


def test_every_stamp_covers_what_its_module_reaches_once_imported(monkeypatch) -> None:
    """A function's stamp is taken when it is decorated, before the rest of its module runs: a
    package module imported further down the file would be missing from it. After importing
    every compiled module, each package function's stamp is still its module's whole digest."""
    reached = {m.__name__ for m in compiled.reached_modules(simulator)}
    assert {"anfekf_bench.sources.simulator", "anfekf_bench.models.motion_terms"} <= reached
    if compiled.numba_njit() is None:
        pytest.skip("numba is not in use")
    for name in (
        "engines.fast", "engines.kernels_bank", "engines.kernels_als", "engines.kernels_swvb",
        "engines.kernels_augmented", "engines.kernels_kalmannet", "engines.tuning",
        "analysis.metrics", "analysis.run_means", "problems.fast", "problems.kalman",
    ):  # fmt: skip
        importlib.import_module(f"anfekf_bench.{name}")
    checked = 0
    for module in [m for n, m in sys.modules.items() if n.startswith("anfekf_bench.")]:
        for value in list(vars(module).values()):
            cache = getattr(value, "_cache", None)
            locator = getattr(getattr(cache, "_impl", None), "locator", None)
            if locator is None or getattr(value, "__module__", None) != module.__name__:
                continue
            assert type(locator).__name__ == "ReachedSourcesLocator", value
            assert locator.get_source_stamp()[1] == compiled.reached_sources_digest(module), value
            assert locator._py_file == module.__file__  # numba's own attributes reach through
            checked += 1
    assert checked >= 40
    # a source edited after the process saw it: a stamp no process matches, never the edit's
    path = str(Path(simulator.__file__).resolve())
    monkeypatch.setitem(compiled._SOURCE_TIMES, path, compiled._SOURCE_TIMES[path] - 1)
    first = compiled.reached_sources_digest(simulator)
    assert "changed after this process read it" in first
    assert compiled.reached_sources_digest(simulator) != first
