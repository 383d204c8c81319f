"""Where a result came from: this package's version and the git commit of its source.

Both are looked up once per process (results written by one process agree byte for byte), never
fail (None when unknown: an installed wheel has no git checkout) and never wait long.
"""

from __future__ import annotations

import functools
import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

PACKAGE = "anfekf-bench"
_SOURCE = Path(__file__).resolve().parent


def source_files(package: Path | None = None) -> list[Path]:
    """The Python sources of this package (or of folder `package`), sorted: every `*.py` but
    those under `__pycache__`, which hold no source (the fast engine's generated loops)."""
    package = _SOURCE if package is None else package
    return sorted(
        path
        for path in package.rglob("*.py")
        if "__pycache__" not in path.relative_to(package).parts
    )


@functools.lru_cache(maxsize=1)
def package_version() -> str:
    """The installed version of anfekf-bench, or 'unknown'."""
    try:
        return version(PACKAGE)
    except PackageNotFoundError:
        return "unknown"


@functools.lru_cache(maxsize=1)
def git_commit() -> str | None:
    """The commit of the git checkout this package runs from, or None (not a checkout, no git)."""
    if not any((p / ".git").exists() for p in (_SOURCE, *_SOURCE.parents)):
        return None
    try:
        done = subprocess.run(
            ["git", "-C", str(_SOURCE), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    commit = done.stdout.strip()
    return commit if done.returncode == 0 and len(commit) in (40, 64) else None


def version_line() -> str:
    """'anfekf-bench 0.1.0 (git 4da8755)': what `anfekf --version` prints."""
    commit = git_commit()
    return f"{PACKAGE} {package_version()}" + (f" (git {commit[:7]})" if commit else "")
