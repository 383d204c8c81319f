"""The `anfekf` command line (typer). Each command is a thin shell over one module."""

from __future__ import annotations

import contextlib
import os
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text
from typer.core import TyperArgument, TyperGroup, TyperOption

# Only light modules at import: `anfekf --version`, `-h` and `kinds` must not pay for numpy,
# pandas, scipy, numba or matplotlib (about 3 s of CPU). Each command imports what it runs.
from .provenance import version_line
from .run_tables import print_comparisons, summary_table, sweep_summary_table
from .signals import (
    exit_code,
    interrupt_behind,
    restore_termination,
    stop_on_termination,
    stopped_by,
)
from .text import one_line, plural

# click's exception classes as typer raises them (typer >= 0.17 vendors its own click): found
# through typer's public BadParameter, so this works with either.
_ClickException = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")
_UsageError = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")
_NoArgsIsHelp = getattr(sys.modules[_UsageError.__module__], "NoArgsIsHelpError", ())


class OneLineUsageErrors(TyperGroup):
    """Command-line usage errors (an unknown option, a value of the wrong type, a missing
    argument) as one `error:` line on stderr with exit code 2, not click's framed box."""

    def main(self, *args, standalone_mode: bool = True, **kwargs):
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            code = super().main(*args, standalone_mode=False, **kwargs)
        except _NoArgsIsHelp as exc:  # `anfekf` alone: the help, as before
            exc.show()
            sys.exit(exc.exit_code)
        except _ClickException as exc:
            message = exc.format_message()
            ctx = getattr(exc, "ctx", None)
            if isinstance(exc, _UsageError) and ctx is not None:
                message += f" (see: {ctx.command_path} --help)"
            err_console.print(
                one_line(f"error: {message}"), markup=False, highlight=False, soft_wrap=True
            )
            sys.exit(exc.exit_code)
        except typer.Abort as exc:  # click's, for a Ctrl-C outside the command's own handlers
            found = interrupt_behind(exc)
            word = "aborted" if found is None else stopped_by(found)
            err_console.print(f"error: {word}", markup=False, highlight=False)
            sys.exit(1 if found is None else exit_code(found))
        except OSError as exc:
            if not writing_stdout(exc):
                raise
            # `anfekf kinds > /dev/full`: the output cannot be written. One line, not rich's
            # traceback (nor Python's "Exception ignored" at exit: stdout is pointed away).
            stdout_gone()
            try:
                sys.stderr.write(one_line(f"error: standard output: cannot write ({exc})") + "\n")
            except (OSError, ValueError):
                pass
            sys.exit(EXIT_OUTPUT_LOST)
        sys.exit(code if isinstance(code, int) else 0)

    def make_context(self, *args, **kwargs):
        try:  # parsing the command line (a Ctrl-C in its first instants lands here)
            return super().make_context(*args, **kwargs)
        except KeyboardInterrupt as exc:
            interrupted(exc)

    def invoke(self, ctx):
        # The reader of our output went away (`anfekf ... | head`): stop quietly with the code a
        # process killed by SIGPIPE has, not click's exit 1 (which `check` uses for a
        # regression) nor a traceback.
        try:
            return super().invoke(ctx)
        except BrokenPipeError:
            stdout_gone()
            raise typer.Exit(EXIT_BROKEN_PIPE) from None
        except KeyboardInterrupt as exc:
            interrupted(exc)


EXIT_BROKEN_PIPE = 128 + 13  # as a process killed by SIGPIPE
EXIT_OUTPUT_LOST = 74  # sysexits' EX_IOERR: stdout cannot be written (a full disk, /dev/full)


def writing_stdout(exc: BaseException) -> bool:
    """Whether `exc` was raised while a rich Console (ours, or typer's for --help) wrote to
    stdout (file descriptor 1): the output cannot be written, a full disk or /dev/full."""
    tb = exc.__traceback__
    while tb is not None:
        writer = tb.tb_frame.f_locals.get("self")
        if isinstance(writer, Console):
            try:
                if writer.file.fileno() == 1:
                    return True
            except (OSError, ValueError, AttributeError):  # a file without a descriptor
                pass
        tb = tb.tb_next
    return False


def interrupted(exc: KeyboardInterrupt) -> None:
    """A Ctrl-C (or SIGTERM, SIGHUP: signals.py) while the command line is parsed or a command
    imports what it runs (this module imports little, so the entry point's own handler no
    longer sees it): typer would exit 130 without a word."""
    err_console.print(f"error: {stopped_by(exc)}", markup=False, highlight=False)
    raise typer.Exit(exit_code(exc)) from None


def stdout_gone() -> None:
    """Point stdout at /dev/null: its reader closed the pipe, and Python's final flush of what
    is left in the buffer must not fail again (that would print an error and exit 120)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no real stdout (tests): nothing to redirect
        pass


# typer writes "<bool>" after every flag in --help, as if it took a value; a flag takes none.
_display_type = TyperOption.display_type_rich


def _no_flag_metavar(self, ctx):
    return None if getattr(self, "is_flag", False) else _display_type(self, ctx)


TyperOption.display_type_rich = _no_flag_metavar
# ... and "<list[Path]>" for an argument that takes several paths: "<path>..." says it plainly.
_argument_type = TyperArgument.display_type_rich


def _plain_list_metavar(self, ctx):
    shown = _argument_type(self, ctx)
    if isinstance(shown, str) and shown.startswith("<list[") and shown.endswith("]>"):
        return f"<{shown[6:-2].lower()}>..."
    return shown


TyperArgument.display_type_rich = _plain_list_metavar
# ... and "{SCENARIO}" for a required argument in the usage line (typer >= 0.2x): the usual
# convention is a bare SCENARIO (required) and [RESULTS_DIR] (optional).
_usage_name = getattr(TyperArgument, "_usage_display_name", None)


def _plain_usage_name(self):
    shown = _usage_name(self)
    more = "..." if shown.endswith("...") else ""
    core = shown.removesuffix("...")
    if core.startswith("{") and core.endswith("}"):
        core = core[1:-1]
    return core + more


if _usage_name is not None:
    TyperArgument._usage_display_name = _plain_usage_name


app = typer.Typer(
    cls=OneLineUsageErrors,
    add_completion=True,
    context_settings={"help_option_names": ["-h", "--help"]},
    no_args_is_help=True,
    help="Monte Carlo benchmark of the EKF against the adaptive neuro-fuzzy EKF (ANFEKF).",
)


class PipeAwareConsole(Console):
    """rich's Console, but a closed stdout (`anfekf ... | head`) raises BrokenPipeError for the
    command to handle (rich's own handler exits 1, which `check` reserves for a regression)."""

    def on_broken_pipe(self) -> None:
        stdout_gone()
        raise BrokenPipeError(32, "the reader of stdout went away")


console = PipeAwareConsole()
err_console = PipeAwareConsole(stderr=True)
WIDE_LOG = 120  # columns for tables when the output is not a terminal


def table_console() -> Console:
    """The console for tables.

    CI logs and pipes get rich's default of 80 columns, which folds wide tables into unreadable
    fragments; a log line has no width limit, so print them wide there.
    """
    if not console.is_terminal and console.width < WIDE_LOG:
        return PipeAwareConsole(file=console.file, width=WIDE_LOG)
    return console


EXIT_USAGE = 2


class EngineChoice(str, Enum):
    """`anfekf run --engine`: filterpy (the reference) or fast (numeric kernels)."""

    filterpy = "filterpy"
    fast = "fast"


class Backend(str, Enum):
    """`anfekf run --backend`: where the Monte Carlo runs execute."""

    local = "local"
    dask = "dask"


def _print_version(value: bool) -> None:
    if value:
        console.print(version_line(), markup=False, highlight=False)
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version",
            "-V",
            callback=_print_version,
            is_eager=True,
            help="Print the version (and git commit) and exit.",
        ),
    ] = False,
) -> None:
    """Monte Carlo benchmark of the EKF against the adaptive neuro-fuzzy EKF (ANFEKF)."""


def fail(message: str, code: int = EXIT_USAGE):
    """Print one line to stderr and exit: the only way a command reports bad input."""
    line = one_line(f"error: {message}")
    err_console.print(line, markup=False, highlight=False, soft_wrap=True)
    raise typer.Exit(code)


@contextmanager
def one_line_errors(
    debug: bool,
    expected: tuple[type[BaseException], ...],
    *,
    prefix: str = "",
    os_error: str | None = None,
) -> Iterator[None]:
    """Report the expected errors (and OSError, when `os_error` names what was being written) as
    one `error:` line with exit code 2; with --debug let them through with their traceback."""
    try:
        yield
    except expected as exc:
        if debug:
            raise
        fail(f"{prefix}{exc}")
    except OSError as exc:
        if debug or os_error is None or writing_stdout(exc):  # stdout's: said at the top
            raise
        fail(f"{os_error}: {exc}")


def _check_out_dir(out: Path) -> None:
    from .arguments import output_folder
    from .outputs import PlanError

    try:
        output_folder(out, "--out")
    except PlanError as exc:
        fail(str(exc))


@app.command()
def run(
    scenario: Annotated[
        Path, typer.Argument(metavar="SCENARIO", help="Scenario YAML file, or a folder of them.")
    ],
    runs: Annotated[
        Optional[int], typer.Option(help="Monte Carlo runs, >= 1 (overrides file).")
    ] = None,
    jobs: Annotated[
        Optional[int], typer.Option(help="Local workers, >= 1 (default: the file's jobs, else 2).")
    ] = None,
    seed: Annotated[Optional[int], typer.Option(help="Root seed, >= 0 (overrides file).")] = None,
    out: Annotated[Path, typer.Option(help="Output folder; results go to OUT/<name>/.")] = Path(
        "results"
    ),
    force: Annotated[
        bool, typer.Option("--force", help="Overwrite a complete earlier result.")
    ] = False,
    skip_existing: Annotated[
        bool,
        typer.Option(
            "--skip-existing",
            help="Keep the scenarios whose output folder holds a complete result; run the others.",
        ),
    ] = False,
    backend: Annotated[
        Optional[Backend],
        typer.Option(help="Run on local processes or a Dask cluster (default: the file's)."),
    ] = None,
    scheduler: Annotated[
        Optional[str],
        typer.Option(metavar="tcp://HOST:PORT", help="Dask scheduler address (--backend dask)."),
    ] = None,
    engine: Annotated[
        Optional[EngineChoice],
        typer.Option(help="filterpy (reference) or fast (numeric kernels; default: the file's)."),
    ] = None,
    debug: Annotated[
        bool, typer.Option("--debug", help="Show tracebacks instead of one-line errors.")
    ] = False,
) -> None:
    """Run Monte Carlo batches of every filter of a scenario and write Parquet results."""
    from .arguments import run_arguments
    from .config import ScenarioError, scenario_files
    from .experiment import (
        OutputExists,
        PlanError,
        check_plan,
        long_plan_line,
        make_plan,
        scenario_folder,
        survey_output,
    )
    from .scenarios import load_scenario, split_problem_files
    from .sweeps import SweepError, cell_plans, expand, validate_sweep

    warnings.showwarning = _one_line_warning  # a library's warning may quote a name
    # The checks the Python API applies too (rather than typer's min=/max=: a multi-line box).
    with one_line_errors(debug, (PlanError,)):
        checked = run_arguments(
            runs=runs, seed=seed, jobs=jobs, engine=engine, backend=backend,
            scheduler=scheduler, force=force, option=lambda name: f"--{name}",
        )  # fmt: skip
    if force and skip_existing:
        fail("--force and --skip-existing: choose one (overwrite complete results, or keep them)")
    kind = checked.backend
    with one_line_errors(debug, (ScenarioError, PlanError)):
        # A problem beyond the robot (`problem: linear`, SPEC 17) has a pipeline of its own.
        files, problems = split_problem_files(scenario_files(scenario))
        plans = [make_plan(*load_scenario(p), **checked.plan_overrides()) for p in files]
    if problems:
        _run_problems(problems, out, runs, seed, jobs, force, skip_existing, debug,
                      checked.engine)  # fmt: skip
        if not files:
            return
    if any(p.engine == "fast" for p in plans):
        warn_fast_without_numba()
    names = [p.name for p in plans]
    if len(set(names)) != len(names):
        fail(f"{scenario}: two scenario files share a name; names must be unique")
    # A sweep's cells are expanded and validated as scenarios now, before anything runs.
    sweeps: dict[str, tuple] = {}
    with one_line_errors(debug, (ScenarioError, PlanError)):
        for path, plan in zip(files, plans, strict=True):
            if plan.scenario.sweep is not None:
                cells = expand(plan.scenario, path)
                overrides = dict(backend=kind, scheduler=scheduler, engine=plan.engine)
                sweeps[plan.name] = (cells, cell_plans(cells, runs=runs, seed=seed, jobs=jobs,
                                                       **overrides))  # fmt: skip
    _check_out_dir(out)
    # Everything that can fail is checked for every scenario before the first one runs (and
    # again by execute, under the folder's lock, before --force removes anything).
    skipped: dict[str, str] = {}  # --skip-existing: scenario -> what its folder holds
    for path, plan in zip(files, plans, strict=True):
        if plan.name in sweeps:  # every cell, and the sweep's folder
            with one_line_errors(debug, (PlanError, OutputExists, SweepError), prefix=f"{path}: "):
                validate_sweep(plan.name, *sweeps[plan.name], out, force=force)
            continue
        with one_line_errors(debug, (PlanError,), prefix=f"{path}: "):
            control_steps = check_plan(plan)
        with one_line_errors(debug, (OutputExists, SweepError), prefix=f"{plan.name}: "):
            if plan.name not in sweeps:
                target = scenario_folder(out, plan.name)
                held = None if force else complete_result(target, plan)
                if held is not None and skip_existing:
                    skipped[plan.name] = held
                    continue
                if held is not None:
                    raise OutputExists(
                        f"{target}: holds a complete result already ({held}); use --force to"
                        " overwrite it, --skip-existing to keep it and run the other scenarios,"
                        " or --out to write elsewhere"
                    )
                survey_output(plan, target, force)
        estimate = long_plan_line(plan, control_steps)  # a long batch says so before it starts
        if estimate is not None:
            console.print(one_line(estimate), markup=False, highlight=False, soft_wrap=True)
    if any(p.engine == "fast" and p.backend.kind == "local" and p.name not in skipped
           for p in plans):  # fmt: skip
        compile_fast_kernels_once()  # after every check: a typo never waits for a compiler
    for plan in plans:
        if plan.name in skipped:
            target = scenario_folder(out, plan.name)
            console.print(
                one_line(f"{plan.name}: {target} holds a complete result ({skipped[plan.name]});"
                         " skipped (--skip-existing)"),
                markup=False, highlight=False, soft_wrap=True,
            )  # fmt: skip
        elif plan.name in sweeps:
            _run_sweep(plan, *sweeps[plan.name], out, force, debug)
        else:
            _run_plan(plan, out, force, debug)


def _run_problems(problems, out, runs, seed, jobs, force, skip_existing, debug,
                  engine=None) -> None:  # fmt: skip
    """Run problem scenarios (SPEC 17: anfekf_bench.problems) and print their tables."""
    from .problems.experiment import ProblemRunError, execute_problem, is_problem_result
    from .problems.report import problem_console_table
    from .storage import FolderBusy

    _check_out_dir(out)
    for path, scenario in problems:
        target = Path(out) / scenario.name
        if skip_existing and not force and is_problem_result(target):
            console.print(
                one_line(f"{scenario.name}: {target} holds a complete result; skipped"
                         " (--skip-existing)"), markup=False, highlight=False, soft_wrap=True,
            )  # fmt: skip
            continue
        on = engine or scenario.engine
        console.print(one_line(f"{scenario.name}: problem {scenario.problem}, running on {on}"),
                      markup=False, highlight=False, soft_wrap=True)  # fmt: skip
        with one_line_errors(debug, (ProblemRunError, FolderBusy), prefix=f"{path}: ",
                             os_error=f"{scenario.name}: cannot write results"):  # fmt: skip
            _, target = execute_problem(scenario, out, runs=runs, seed=seed, jobs=jobs,
                                        force=force, engine=engine)  # fmt: skip
        table_console().print(problem_console_table(target))
        console.print(one_line(f"results written to {target}"), markup=False, highlight=False,
                      soft_wrap=True)  # fmt: skip


def warn_fast_without_numba() -> None:
    """Say once when `fast` will run as plain Python (numba missing): it works, but slowly."""
    from .runner import fast_compiled

    if fast_compiled("fast") is False:
        err_console.print(
            "warning: --engine fast without numba: its kernels run as plain Python (several"
            " times slower than compiled); install numba with `pip install -e '.[fast]'`"
            " (`make setup` does). The manifest records it (fast_compiled: false).",
            markup=False, highlight=False, soft_wrap=True,
        )  # fmt: skip


def compile_fast_kernels_once() -> None:
    """The fast engine's first run compiles its numba kernels (a minute or two on a laptop):
    when numba's cache does not hold them, say so in one line and compile them here, once, into
    the cache every worker then loads (in a fraction of a second) instead of each compiling."""
    from .engines import fast

    if fast.kernels_cached() is False:
        err_console.print(
            f"compiling the fast engine's kernels once ({fast.COMPILE_ESTIMATE}; cached"
            " afterwards)",
            markup=False, highlight=False, soft_wrap=True,
        )  # fmt: skip
        fast.warm_up()


def complete_result(target: Path, plan) -> str | None:
    """What a complete result in `target` holds ('the same runs and seed', 'runs 20, seed 7'),
    or None when the folder holds no complete result (no manifest.json)."""
    from .storage import MANIFEST_FILE, ResultsError, read_manifest

    if not (target / MANIFEST_FILE).is_file():
        return None
    try:
        manifest = read_manifest(target)
    except ResultsError:
        return "its manifest.json is unreadable"
    if manifest.get("fingerprint") == plan.fingerprint():
        return f"this scenario with the same {plan.runs} runs and seed {plan.seed}"
    return f"{manifest.get('runs', '?')} runs, seed {manifest.get('seed', '?')}"


class RunRateColumn(ProgressColumn):
    """Runs per second (per minute when slower), from rich's moving estimate; a task's `unit`
    field names another unit."""

    def render(self, task) -> Text:
        speed = task.finished_speed or task.speed
        if not speed:
            return Text("", style="progress.data.speed")
        unit = task.fields.get("unit", "runs")  # a training task counts gradient steps
        shown = f"{speed:.2g} {unit}/s" if speed >= 1 else f"{speed * 60:.2g} {unit}/min"
        return Text(shown, style="progress.data.speed")


def run_progress() -> Progress:
    """The progress bar of `anfekf run`: one task per scenario or sweep, runs done of all, the
    rate, the time so far and the time left (ETA)."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        RunRateColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    )


def _run_sweep(plan, cells, plans, out: Path, force: bool, debug: bool) -> None:
    """Every cell of a sweep with one progress bar over all its runs, then the sweep table."""
    from .experiment import FolderBusy, OutputExists, PlanError
    from .filters.custom import CustomFilterFailed
    from .runner import BackendUnavailable
    from .sources.simulator import RouteNotCompleted
    from .sweeps import SweepError, run_sweep

    progress = run_progress()
    total = sum(p.runs for p in plans)
    task = progress.add_task(f"{plan.name}: {len(cells)} cells", total=total)

    reused = 0

    def on_cell(cell, what: str) -> None:
        # One line that changes, not two printed lines per cell; the table comes at the end.
        nonlocal reused
        shown = ", ".join(f"{k} = {v:g}" for k, v in cell.coords.items())
        progress.update(task, description=one_line(f"{plan.name} {cell.name} ({shown})"))
        if what.startswith("complete"):
            reused += 1
            progress.advance(task, plans[cell.index].runs)

    def on_start(_action: str, done: int, _total: int) -> None:
        progress.advance(task, done)

    try:
        with (
            one_line_errors(debug, (BackendUnavailable,)),
            one_line_errors(
                debug,
                (
                    OutputExists,
                    RouteNotCompleted,
                    PlanError,
                    FolderBusy,
                    SweepError,
                    CustomFilterFailed,
                ),  # fmt: skip
                prefix=f"{plan.name}: ",
                os_error=f"{plan.name}: cannot write results",
            ),
            progress,
        ):
            table, target = run_sweep(
                plan.name, plan.scenario.sweep.axes, cells, plans, out, force=force,
                on_cell=on_cell, on_start=on_start, on_result=lambda _: progress.advance(task),
            )  # fmt: skip
            progress.update(task, description=f"{plan.name}: {plural(len(cells), 'cell')}")
    except KeyboardInterrupt as exc:
        if debug:
            raise
        fail(
            f"{plan.name}: {stopped_by(exc)}; finished cells and runs are saved in"
            f" {Path(out) / plan.name}: run the same command again to resume",
            code=exit_code(exc),
        )
    table_console().print(sweep_summary_table(plan.name, table, plans[0].runs))
    again = f" ({reused} complete already: reused)" if reused else ""
    console.print(
        f"sweep {plan.name}: {plural(len(cells), 'cell')} x {plans[0].runs} runs{again} written"
        f" to {target} (sweep.parquet; `anfekf report {out}` draws it)",
        markup=False,
        highlight=False,
    )


def _run_plan(plan, out: Path, force: bool, debug: bool) -> None:
    from .experiment import FolderBusy, OutputExists, PlanError, execute
    from .filters.custom import CustomFilterFailed
    from .runner import BackendUnavailable
    from .sources.simulator import RouteNotCompleted
    from .storage import RUNS_DIR

    progress = run_progress()
    task = None
    saved = 0  # runs on disk in <out>/<name>/.runs, for the message if interrupted

    def on_start(action: str, done: int, total: int) -> None:
        nonlocal task, saved
        console.print(
            one_line(f"{plan.name}: {action}"), markup=False, highlight=False, soft_wrap=True
        )
        task = progress.add_task(plan.name, total=total, completed=done)
        saved = done

    def on_result(_: dict) -> None:
        nonlocal saved
        saved += 1
        progress.advance(task)

    try:
        with (
            one_line_errors(debug, (BackendUnavailable,)),
            one_line_errors(
                debug,
                (OutputExists, RouteNotCompleted, PlanError, FolderBusy, CustomFilterFailed),
                prefix=f"{plan.name}: ",
                os_error=f"{plan.name}: cannot write results",
            ),
            progress,
        ):
            records, target = execute(
                plan, out, force=force, on_start=on_start, on_result=on_result,
                progress=progress,
            )  # fmt: skip
    except KeyboardInterrupt as exc:
        if debug:
            raise
        store = Path(out) / plan.name / RUNS_DIR  # what is there (held runs are saved on Ctrl-C)
        with contextlib.suppress(OSError):
            saved = sum(1 for _ in store.glob("run-*.npz"))
        fail(
            f"{plan.name}: {stopped_by(exc)}; {saved} of {plan.runs} runs are saved in"
            f" {store}: run the same command again to resume",
            code=exit_code(exc),
        )
    tables = table_console()
    tables.print(summary_table(f"{plan.name}: {plan.runs} runs, seed {plan.seed}", records))
    print_comparisons(tables, target)
    console.print(
        one_line(f"results written to {target}"), markup=False, highlight=False, soft_wrap=True
    )


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A library's warning (matplotlib's about a glyph, say) as one escaped line on stderr."""
    err_console.print(
        one_line(f"warning: {category.__name__}: {message}"),
        markup=False,
        highlight=False,
        soft_wrap=True,
    )


@app.command()
def report(
    results: Annotated[
        Optional[list[Path]],
        typer.Argument(
            metavar="RESULTS_DIR",
            help="Result folders: a scenario's folder or a parent of several (default: results).",
            show_default=False,
        ),
    ] = None,
    out: Annotated[Path, typer.Option(help="Report folder.")] = Path("results/report"),
    image_format: Annotated[
        str, typer.Option("--format", metavar="png|svg|pdf", help="Figure file format.")
    ] = "png",
    dpi: Annotated[
        int,
        typer.Option(metavar="N", help="Resolution of PNG figures (and of the HTML's images)."),
    ] = 110,
    jobs: Annotated[
        int,
        typer.Option(
            metavar="N",
            help="Worker processes that draw the figures while the report is built, at most one"
            " per CPU (1: all in this process). The files are the same.",
        ),
    ] = 2,
    debug: Annotated[
        bool, typer.Option("--debug", help="Show tracebacks instead of one-line errors.")
    ] = False,
) -> None:
    """Draw figures and tables of saved results: report.md and report.html (never re-runs)."""
    if not 1 <= jobs <= 64:
        fail(f"--jobs: must be an integer from 1 to 64 (got {jobs})")
    # Imported here so that `anfekf run` does not pay for matplotlib. The figure workers start
    # first: they are ready by the time this process has imported the report and read results.
    from .report.render import figure_workers, render_pool

    pool = render_pool(figure_workers(jobs))
    try:
        done, sweep_folders = _write_report(results, out, image_format, dpi, jobs, debug)
    except BaseException:
        if pool is not None:
            pool.stop()  # a command that fails ends now, not once its workers have started
        raise
    from .report import HTML_FILE, REPORT_FILE, rich_table

    if done.rows:
        table_console().print(rich_table(done.rows))
    for warning in done.warnings:
        console.print(f"warning: {warning}", markup=False, highlight=False, soft_wrap=True)
    # the report's tables (worst_case.parquet and .csv) are files too, not figures
    figures = sum(1 for p in done.files if p.suffix[1:] in ("png", "svg", "pdf"))
    pages = [str(p) for p in done.files if p.name in (REPORT_FILE, HTML_FILE)]
    shown = done.scenarios or not (sweep_folders or done.problems)
    parts = [plural(len(done.scenarios), "scenario")] if shown else []
    if done.problems:
        parts.append(plural(done.problems, "problem result"))
    if sweep_folders:
        parts.append(plural(len(sweep_folders), "sweep"))
    drawn = (
        f"; figures drawn in {done.figure_workers} worker processes" if done.figure_workers else ""
    )
    console.print(
        f"report of {' and '.join(parts)} ({plural(figures, 'figure')}) written to"
        f" {' and '.join(pages)}{drawn}",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )


def _write_report(results, out: Path, image_format: str, dpi: int, jobs: int, debug: bool):
    """`anfekf report`'s checks and its `write_report`: (what it wrote, the sweep folders)."""
    from .report import ImageFormat, write_report
    from .report.results import find_sweeps
    from .storage import ResultsError

    warnings.showwarning = _one_line_warning  # a library's warning may quote a name
    formats = [f.value for f in ImageFormat]
    if image_format not in formats:
        fail(f"--format: {image_format!r} is not one of {', '.join(formats)}")
    if not 10 <= dpi <= 1200:
        fail(f"--dpi: must be an integer from 10 to 1200 (got {dpi})")
    _check_out_dir(out)
    folders = results or [Path("results")]
    with one_line_errors(debug, (ResultsError,), os_error=f"{out}: cannot write the report"):
        sweep_folders = find_sweeps(folders)
        # One report of everything: scenarios, real data and sweeps.
        done = write_report(
            folders, out, ImageFormat(image_format), dpi=dpi, sweeps=sweep_folders, jobs=jobs
        )
    return done, sweep_folders


@app.command()
def check(
    results: Annotated[
        Path, typer.Argument(help="Results folder of `anfekf run` (or one scenario's folder).")
    ],
    baseline: Annotated[
        Optional[Path],
        typer.Option(help="Baseline JSON to compare with; without it only the claims are checked."),
    ] = None,
    update: Annotated[
        bool,
        typer.Option(
            "--update",
            help="Rewrite BASELINE from RESULTS, on purpose (docs/how-to/regression-gate.md).",
        ),
    ] = False,
    strict: Annotated[
        bool, typer.Option("--strict", help="An inconclusive claim fails the gate too.")
    ] = False,
    debug: Annotated[
        bool, typer.Option("--debug", help="Show tracebacks instead of one-line errors.")
    ] = False,
) -> None:
    """Regression gate: compare results with a baseline and check the scenarios' claims (exit 1)."""
    from .analysis.gate import BaselineError, print_report, run_check
    from .problems.gate import read_problem_summaries
    from .storage import ResultsError

    with one_line_errors(debug, (ResultsError, BaselineError)):
        problems = read_problem_summaries(results)
        found = run_check(results, baseline, update=update, strict=strict, problems=problems)
    try:
        print_report(found, table_console())
        sys.stdout.flush()
    except BrokenPipeError:  # `anfekf check ... | head`: the verdict stands, the rest is unread
        stdout_gone()
    raise typer.Exit(found.exit_code)


@app.command()
def bench(
    out: Annotated[Path, typer.Option(help="JSON file for the figures.")] = Path(
        "results/bench.json"
    ),
    configs: Annotated[
        Path, typer.Option(help="Folder of the paper's scenario files (each is run end to end).")
    ] = Path("configs"),
    quick: Annotated[
        bool,
        typer.Option(
            "--quick", help="Tiny sizes (2 runs, short route): the machinery, not the targets."
        ),
    ] = False,
    debug: Annotated[
        bool, typer.Option("--debug", help="Show tracebacks instead of one-line errors.")
    ] = False,
) -> None:
    """Measure harness overhead, ANFEKF cost, 2-worker speedup, memory, Parquet size, wall time."""
    from .bench import FULL, QUICK, BenchError, bench_table, run_bench
    from .config import ScenarioError

    with one_line_errors(
        debug, (BenchError, ScenarioError), os_error=f"{out}: cannot write the bench figures"
    ):
        found = run_bench(configs, out, QUICK if quick else FULL, say=console.print)
    table_console().print(bench_table(found))
    console.print(f"bench figures written to {out}", highlight=False)


@app.command()
def kinds(
    names: Annotated[
        Optional[list[str]],
        typer.Argument(
            metavar="KIND", help="Kinds to show (default: every kind).", show_default=False
        ),
    ] = None,
) -> None:
    """List every filter kind (or the KINDs named): what it adapts, which engines run it, its
    parameters and defaults."""
    from .engines import fast_support
    from .filters.registry import (
        KINDS,
        adapts_line,
        capabilities,
        problems_of,
        unsupported_reason,
    )

    fast_support.register()  # the fast engine's kinds, without importing numba and its kernels
    unknown = [n for n in names or () if n not in KINDS]
    if unknown:
        fail(f"kinds: unknown kind {unknown[0]!r} (known: {', '.join(KINDS)})")
    for kind in dict.fromkeys(names or KINDS):
        info = capabilities(kind)
        console.print(f"{kind}: {info.doc}", markup=False, highlight=False, soft_wrap=True)
        console.print(
            f"  adapts: {adapts_line(info)}; engines: {', '.join(info.engines)}",
            markup=False, highlight=False, soft_wrap=True,
        )  # fmt: skip
        others = sorted(problems_of(kind) - {"robot"})
        runs_on = ", ".join(["robot", *others]) if others else (
            f"robot only ({unsupported_reason(kind, 'linear').split(': ', 1)[1]})"
        )  # fmt: skip
        console.print(f"  problems: {runs_on}", markup=False, highlight=False, soft_wrap=True)
        for name, default, description in info.params:
            line = f"  {name} = {default}" + (f": {description}" if description else "")
            console.print(one_line(line), markup=False, highlight=False, soft_wrap=True)


@app.command()
def init(
    path: Annotated[
        Path, typer.Argument(help="Where to write the starter scenario.", metavar="PATH")
    ] = Path("scenario.yaml"),
) -> None:
    """Write a commented starter scenario that `anfekf run` accepts (never overwrites a file)."""
    import errno

    from .starter import write_starter

    try:
        name = write_starter(path)
    except FileExistsError:
        fail(f"{path}: already exists; choose another PATH (init never overwrites a file)")
    except OSError as exc:
        if exc.errno in (errno.ENOENT, errno.ENOTDIR):
            fail(f"{path.parent}: no such folder")
        fail(f"{path}: cannot write the starter scenario ({exc.strerror or exc})")
    console.print(
        one_line(f"starter scenario {name!r} written to {path}; run it with: anfekf run {path}"),
        markup=False, highlight=False, soft_wrap=True,
    )  # fmt: skip


def main() -> None:  # pragma: no cover - console entry point
    stop_on_termination()
    try:
        app()
    finally:
        restore_termination()
