"""The command line as a new user meets it: --version, -h, shell completion, flags that take no
value, output piped into `head`, and a folder run that checks every output folder first."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import EXIT_BROKEN_PIPE, app
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.provenance import package_version
from anfekf_bench.scenarios import load_scenario

from .conftest import small_scenario, write_scenario

runner = CliRunner()
COMMANDS = ("run", "report", "check", "bench")
# The installed console script (completion keys on the program name), else the same entry point.
_SCRIPT = Path(sys.executable).with_name("anfekf")
ANFEKF = (
    [str(_SCRIPT)]
    if _SCRIPT.is_file()
    else [
        sys.executable,
        "-c",
        "import sys; sys.argv[0] = 'anfekf'; from anfekf_bench.cli import main; main()",
    ]
)


def test_version_names_the_package_version():
    for flag in ("--version", "-V"):
        result = runner.invoke(app, [flag])
        assert result.exit_code == 0, result.output
        assert result.output.startswith(f"anfekf-bench {package_version()}")


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_short_help_and_no_bool_metavar(command):
    """-h is --help; a flag is shown without '<bool>' (it takes no value) and without a
    '--no-...' twin."""
    args = ([command] if command else []) + ["-h"]
    result = runner.invoke(app, args, env={"COLUMNS": "120"})
    assert result.exit_code == 0, result.output
    assert "Usage:" in result.output
    assert "<bool>" not in result.output and "--no-" not in result.output
    assert "list[" not in result.output  # several paths read "<path>..."
    if command in ("run", "report", "check"):
        assert "--debug" in result.output


def test_help_offers_shell_completion():
    result = runner.invoke(app, ["--help"], env={"COLUMNS": "120"})
    assert "--install-completion" in result.output and "--show-completion" in result.output


def test_shell_completion_completes_commands_and_options():
    env = {**os.environ, "_ANFEKF_COMPLETE": "complete_bash", "COMP_CWORD": "1"}
    done = subprocess.run(
        [*ANFEKF], env={**env, "COMP_WORDS": "anfekf rep"}, capture_output=True, text=True
    )
    assert done.returncode == 0 and done.stdout.split() == ["report"], done
    env["COMP_CWORD"] = "2"
    done = subprocess.run(
        [*ANFEKF], env={**env, "COMP_WORDS": "anfekf run --fo"}, capture_output=True, text=True
    )
    assert done.returncode == 0 and "--force" in done.stdout.split(), done


# --------------------------------------------------------------------------- output into `head`


@pytest.fixture(scope="module")
def checked_results(tmp_path_factory) -> Path:
    """A tiny result whose one claim holds: `anfekf check` on it passes (exit 0)."""
    root = tmp_path_factory.mktemp("pipe")
    doc = small_scenario(
        name="piped",
        runs=2,
        record_every=8,
        claims=[{"filter": "anfekf", "vs": "ekf", "metric": "rmse_pos", "at_most": 1000.0}],
    )
    scenario, world = load_scenario(write_scenario(root / "piped.yaml", doc))
    execute(make_plan(scenario, world, None, None, 1), root / "results")
    return root / "results"


def _closed_reader(args: list[str]) -> subprocess.CompletedProcess:
    """Run the command line with a stdout whose reader is already gone, as after `| head -1`."""
    read, write = os.pipe()
    os.close(read)  # the reader went away: every write to the pipe fails with EPIPE
    try:
        proc = subprocess.run(
            [*ANFEKF, *args],
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "COLUMNS": "120"},
            timeout=300,
        )
    finally:
        os.close(write)
    return proc


def test_check_piped_into_head_keeps_its_verdict(checked_results):
    """`anfekf check ... | head` must not look like a regression: exit 0 when the gate passes,
    no traceback, no 'Exception ignored' message."""
    alone = runner.invoke(app, ["check", str(checked_results)])
    assert alone.exit_code == 0, alone.output
    done = _closed_reader(["check", str(checked_results)])
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr
    assert "BrokenPipe" not in done.stderr


def test_other_commands_piped_into_head_stop_quietly(checked_results, tmp_path):
    done = _closed_reader(["report", str(checked_results), "--out", str(tmp_path / "r")])
    assert done.returncode == EXIT_BROKEN_PIPE, done.stderr
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr


# --------------------------------------------------------------------------- a folder of scenarios


@pytest.fixture
def two_scenarios(tmp_path) -> Path:
    folder = tmp_path / "configs"
    folder.mkdir()
    for name in ("alpha", "beta"):
        write_scenario(folder / f"{name}.yaml", small_scenario(name=name, runs=2, record_every=8))
    return folder


def test_folder_run_checks_every_output_folder_before_running_any(two_scenarios, tmp_path):
    """beta already complete: the folder run stops with exit 2 before alpha runs."""
    out = tmp_path / "out"
    first = runner.invoke(app, ["run", str(two_scenarios / "beta.yaml"), "--out", str(out)])
    assert first.exit_code == 0, first.output
    before = (out / "beta" / "manifest.json").read_bytes()
    result = runner.invoke(app, ["run", str(two_scenarios), "--out", str(out)])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: beta: ")
    assert "complete result" in lines[0] and "--skip-existing" in lines[0]
    assert not (out / "alpha").exists()  # nothing ran, nothing was created
    assert "alpha" not in result.stdout
    assert (out / "beta" / "manifest.json").read_bytes() == before


def test_skip_existing_runs_the_others(two_scenarios, tmp_path):
    out = tmp_path / "out"
    assert (
        runner.invoke(app, ["run", str(two_scenarios / "beta.yaml"), "--out", str(out)]).exit_code
        == 0
    )
    before = (out / "beta" / "manifest.json").read_bytes()
    result = runner.invoke(app, ["run", str(two_scenarios), "--out", str(out), "--skip-existing"])
    assert result.exit_code == 0, result.output
    assert re.search(r"beta: .*complete result.*skipped \(--skip-existing\)", result.stdout)
    assert (out / "alpha" / "manifest.json").is_file()
    assert (out / "beta" / "manifest.json").read_bytes() == before  # kept as it was
    both = runner.invoke(
        app, ["run", str(two_scenarios), "--out", str(out), "--skip-existing", "--force"]
    )
    assert both.exit_code == 2 and "--skip-existing" in both.stderr and "--force" in both.stderr
