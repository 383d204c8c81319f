"""The `anfekf` command line (typer). Each command is a thin shell over one module."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from .config import ScenarioError, load_scenario, scenario_files
from .experiment import OutputExists, execute, make_plan
from .simulation import RouteNotCompleted

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Monte Carlo benchmark of the EKF against the adaptive neuro-fuzzy EKF (ANFEKF).",
)
console = Console()
err_console = Console(stderr=True)

EXIT_USAGE = 2


@app.callback()
def _root() -> None:
    """Monte Carlo benchmark of the EKF against the adaptive neuro-fuzzy EKF (ANFEKF)."""


def fail(message: str, code: int = EXIT_USAGE):
    """Print one line to stderr and exit: the only way a command reports bad input."""
    err_console.print(f"error: {message}", markup=False, highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def _fmt(x, digits: int = 3) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{digits}f}"


def summary_table(title: str, records: list[dict]) -> Table:
    table = Table(title=title, title_justify="left")
    for col in ("filter", "runs", "diverged", "RMSE pos (m)", "RMSE head (deg)", "ANEES", "in bounds"):
        table.add_column(col, justify="left" if col == "filter" else "right")
    for r in records:
        table.add_row(
            r["filter"],
            str(r["runs"]),
            str(r["diverged"]),
            _fmt(r["rmse_pos"]),
            _fmt(math.degrees(r["rmse_heading"]) if r["rmse_heading"] is not None else None),
            _fmt(r["anees"], 2),
            "-" if r["nees_in_bounds"] is None else f"{100 * r['nees_in_bounds']:.1f} %",
        )
    return table


def _check_out_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        fail(f"{out}: --out must be a folder, but a file of that name exists")
    probe = out
    while not probe.exists():
        probe = probe.parent
    import os

    if not os.access(probe, os.W_OK):
        fail(f"{out}: --out is not writable")


@app.command()
def run(
    scenario: Annotated[Path, typer.Argument(help="Scenario YAML file, or a folder of them.")],
    runs: Annotated[Optional[int], typer.Option(min=1, help="Monte Carlo runs (overrides file).")] = None,
    jobs: Annotated[Optional[int], typer.Option(min=1, help="joblib workers (default: the file's jobs, else 2).")] = None,
    seed: Annotated[Optional[int], typer.Option(min=0, help="Root seed (overrides file).")] = None,
    out: Annotated[Path, typer.Option(help="Output folder; results go to OUT/<name>/.")] = Path(
        "results"
    ),
    force: Annotated[bool, typer.Option(help="Overwrite a complete earlier result.")] = False,
    debug: Annotated[bool, typer.Option(help="Show tracebacks instead of one-line errors.")] = False,
) -> None:
    """Run Monte Carlo batches of every filter of a scenario and write Parquet results."""
    try:
        plans = [make_plan(*load_scenario(p), runs, seed, jobs) for p in scenario_files(scenario)]
    except ScenarioError as exc:
        if debug:
            raise
        fail(str(exc))
    names = [p.name for p in plans]
    if len(set(names)) != len(names):
        fail(f"{scenario}: two scenario files share a name; names must be unique")
    _check_out_dir(out)
    for plan in plans:
        _run_plan(plan, out, force, debug)


def _run_plan(plan, out: Path, force: bool, debug: bool) -> None:
    progress = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )
    task = None

    def on_start(action: str, done: int, total: int) -> None:
        nonlocal task
        console.print(f"{plan.name}: {action}", highlight=False)
        task = progress.add_task(plan.name, total=total, completed=done)

    def on_result(_: dict) -> None:
        progress.advance(task)

    try:
        with progress:
            records, target = execute(plan, out, force=force, on_start=on_start, on_result=on_result)
    except (OutputExists, RouteNotCompleted) as exc:
        if debug:
            raise
        fail(f"{plan.name}: {exc}")
    except OSError as exc:
        if debug:
            raise
        fail(f"{plan.name}: cannot write results: {exc}")
    console.print(summary_table(f"{plan.name}: {plan.runs} runs, seed {plan.seed}", records))
    console.print(f"results written to {target}", highlight=False)


def main() -> None:  # pragma: no cover - console entry point
    app()

