"""The arguments of a run and of a report, checked in one place for the command line and the
Python API (docs/HARDENING.md, "Hardening 4").

typer types the command line's values, but the API is called with anything: `runs=True` (a
bool is an int in Python), `runs=2.5`, `force="no"` (truthy), `engine="bogus"`, a file as
`out`. Each check here names the argument as the caller spells it (`--runs` on the command
line, `runs` in Python) and raises `PlanError` with one line: `<argument>: <what is allowed>
(got <value>)`. Nothing is touched before every argument passed.
"""

from __future__ import annotations

import operator
import os
import typing
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from .config import MAX_JOBS, MAX_RUNS, MAX_SEED, Engine, one_line
from .outputs import OutputExists, PlanError, check_not_nested
from .storage import output_path_problem

ENGINES = typing.get_args(Engine)
BACKENDS = ("local", "dask")
SHOWN_VALUE = 60  # characters of a refused value quoted in the message


def shown(value: object) -> str:
    """A refused value as the message quotes it: its repr, escaped, at most SHOWN_VALUE long."""
    text = one_line(repr(value))
    return text if len(text) <= SHOWN_VALUE else text[: SHOWN_VALUE - 3] + "..."


def count(value: object, name: str, least: int, most: int) -> int | None:
    """An integer from `least` to `most` (a bool is not one; numpy's integers are), or None."""
    if value is None:
        return None
    try:
        if isinstance(value, bool):
            raise TypeError
        number = operator.index(value)  # ints and numpy integers, never a float or a string
    except TypeError:
        raise PlanError(
            f"{name}: must be an integer from {least} to {most} (got {shown(value)})"
        ) from None
    if number < least:
        raise PlanError(f"{name}: must be an integer >= {least} (got {number})")
    if number > most:
        raise PlanError(f"{name}: must be an integer <= {most} (got {number})")
    return int(number)


def flag(value: object, name: str) -> bool:
    """True or False itself: `"no"`, 1 or None would be read by their truth."""
    if not isinstance(value, bool):
        raise PlanError(f"{name}: must be True or False (got {shown(value)})")
    return value


def choice(value: object, name: str, allowed: Iterable[str]) -> str | None:
    """One of `allowed` (or None: the scenario's own)."""
    allowed = tuple(allowed)
    if value is None:
        return None
    value = getattr(value, "value", value)  # the command line's Enum members
    if not isinstance(value, str) or value not in allowed:
        raise PlanError(f"{name}: must be one of {', '.join(allowed)} (got {shown(value)})")
    return value


def text(value: object, name: str, what: str) -> str | None:
    """A string (or None)."""
    if value is not None and not isinstance(value, str):
        raise PlanError(f"{name}: must be {what} (got {shown(value)})")
    return value


def path(value: object, name: str) -> Path:
    """A path given as a str or os.PathLike (bytes paths and NUL characters are refused)."""
    try:
        if isinstance(value, (str, os.PathLike)):
            found = os.fspath(value)
            if isinstance(found, str) and found and "\0" not in found:
                return Path(found)
    except TypeError:  # a PathLike whose __fspath__ returns something else
        pass
    raise PlanError(f"{name}: must be a non-empty path (str or os.PathLike, no NUL) (got"
                    f" {shown(value)})")  # fmt: skip


def output_folder(value: object, name: str) -> Path:
    """A path that can be created or written as an output folder (not a file, writable); the
    message names the folder first, then the argument (`results: out must be a folder, ...`)."""
    folder = path(value, name)
    problem = output_path_problem(folder, folder=True, option=name)
    if problem:
        raise PlanError(f"{folder}: {problem}")
    return folder


def scenario_target(out: Path, name: str, option: str) -> Path:
    """`out/<name>`, refused (PlanError) when it would sit inside another result's folder or run
    store (outputs.check_not_nested; `execute` checks it again, under the folder's lock)."""
    try:
        check_not_nested(Path(out) / name)
    except OutputExists as exc:
        raise PlanError(f"{option}: {exc}") from None
    return Path(out) / name


def callback(value: object, name: str) -> Callable | None:
    if value is not None and not callable(value):
        raise PlanError(f"{name}: must be a function or None (got {shown(value)})")
    return value


@dataclass(frozen=True)
class RunArguments:
    """A run's overrides, checked: None keeps the scenario file's value."""

    runs: int | None
    seed: int | None
    jobs: int | None
    engine: str | None
    backend: str | None
    scheduler: str | None
    force: bool

    def plan_overrides(self) -> dict:
        """make_plan's keyword arguments besides the scenario and world."""
        return dict(runs=self.runs, seed=self.seed, jobs=self.jobs, backend=self.backend,
                    scheduler=self.scheduler, engine=self.engine)  # fmt: skip


def run_arguments(
    *,
    runs: object = None,
    seed: object = None,
    jobs: object = None,
    engine: object = None,
    backend: object = None,
    scheduler: object = None,
    force: object = False,
    option: Callable[[str], str] = str,
) -> RunArguments:
    """Check a run's arguments; `option` spells an argument's name as its caller knows it
    (the command line: `lambda n: "--" + n`)."""
    return RunArguments(
        runs=count(runs, option("runs"), 1, MAX_RUNS),
        seed=count(seed, option("seed"), 0, MAX_SEED),
        jobs=count(jobs, option("jobs"), 1, MAX_JOBS),
        engine=choice(engine, option("engine"), ENGINES),
        backend=choice(backend, option("backend"), BACKENDS),
        scheduler=text(scheduler, option("scheduler"), "a Dask address like tcp://HOST:PORT"),
        force=flag(force, option("force")),
    )


def result_paths(results: object, name: str) -> list[Path]:
    """One path (str or os.PathLike), or an iterable of them (or of objects with a `folder`:
    the API's results), as a list; at least one."""
    if isinstance(results, (str, os.PathLike)):
        return [path(results, name)]
    if isinstance(results, (bytes, dict)) or not isinstance(results, Iterable):
        raise PlanError(f"{name}: must be a result folder or a list of them (got {shown(results)})")
    found = [path(getattr(r, "folder", r), f"{name}[{i}]") for i, r in enumerate(results)]
    if not found:
        raise PlanError(f"{name}: must name at least one result folder (got none)")
    return found
