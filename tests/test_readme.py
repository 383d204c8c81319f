"""The README and the documentation site (docs/, mkdocs.yml) against the code and the results.

- The generated parts (anfekf_bench.docgen: the scenario keys, the filter kinds, the command
  line, the bench figures, the JSON Schemas) must equal what the code and results/bench.json
  give today: a new key, kind, parameter, option or bench run fails here until `make readme`.
- The numbers the README and docs/results/paper.md show must be those of the committed results.
- Every command the README shows runs in CI (.ci/run), or is covered by what CI runs.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from anfekf_bench import docgen
from anfekf_bench.config import Scenario
from anfekf_bench.filters.registry import SPEC_BY_KIND

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SCENARIO_PAGE = ROOT / "docs" / "reference" / "scenario.md"
FILTERS_PAGE = ROOT / "docs" / "reference" / "filters.md"
CLI_PAGE = ROOT / "docs" / "reference" / "cli.md"
PAPER_PAGE = ROOT / "docs" / "results" / "paper.md"
MAX_README_LINES = 215  # the front page: commands, findings with intervals, then links


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


# --------------------------------------------------------------------------- generated parts


def test_generated_docs_match_the_code(capsys):
    assert docgen.main(["--root", str(ROOT), "--check"]) == 0, capsys.readouterr().out


def test_every_field_has_a_meaning():
    assert docgen.undocumented() == []


def test_the_tables_name_every_key_kind_and_parameter_with_its_default():
    text = _text(SCENARIO_PAGE)
    for name in Scenario.model_fields:
        assert f"| `{name}` |" in text, name
    # The defaults the issue names, as a user reads them.
    for row in ("| `runs` | integer >= 1 | `50` |", "| `seed` | integer >= 0 | `0` |",
                "| `record_every` | integer >= 1 | `1` |", "| `engine` |", "| `steps_table` |",
                "| `claims` |", "| `compare` |",
                "| `filters` | list of mapping | `[{name: ekf, kind: ekf}]` |"):  # fmt: skip
        assert row in text, row
    text = _text(FILTERS_PAGE)
    for kind, spec in SPEC_BY_KIND.items():
        assert f"**`{kind}`**" in text, kind
        for name, field in spec.model_fields.items():
            if name not in ("name", "kind"):
                assert f"| `{field.alias or name}` |" in text, (kind, name)
    assert "| `window` | integer >= 2 | `20` |" in text  # an ANFEKF hyper-parameter


def test_the_cli_page_names_every_command_and_option():
    import typer.main

    from anfekf_bench.cli import app

    text = _text(CLI_PAGE)
    root = typer.main.get_command(app)
    for name, command in root.commands.items():
        assert f"## `anfekf {name}`" in text, name
        for param in command.params:
            for opt in param.opts:
                if opt.startswith("-"):
                    assert opt in text, (name, opt)
    assert "`--engine <filterpy|fast>`" in text


def _copy_generated_sources(root: Path) -> None:
    """The files docgen reads and writes, under a scratch root."""
    for rel in [*docgen.TARGETS, *docgen.SCHEMAS, str(docgen.BENCH_FILE)]:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / rel, root / rel)
    shutil.copytree(ROOT / "configs", root / "configs")


def test_docgen_check_command(tmp_path, capsys):
    _copy_generated_sources(tmp_path)
    args = ["--root", str(tmp_path)]
    assert docgen.main([*args, "--check"]) == 0
    page = tmp_path / "docs" / "reference" / "scenario.md"
    page.write_text(_text(page).replace("| `runs` | integer >= 1 | `50` |", "| x |"), "utf-8")
    (tmp_path / "docs" / "scenario.schema.json").write_text("{}\n", encoding="utf-8")
    assert docgen.main([*args, "--check"]) == 1
    out = capsys.readouterr().out
    assert "scenario.md" in out and "scenario.schema.json" in out and "make readme" in out
    assert docgen.main(args) == 0
    assert docgen.main([*args, "--check"]) == 0


def test_a_page_without_its_generated_block_is_an_error(tmp_path, capsys):
    _copy_generated_sources(tmp_path)
    page = tmp_path / "docs" / "reference" / "cli.md"
    page.write_text("# Command line\n", encoding="utf-8")
    assert docgen.main(["--root", str(tmp_path), "--check"]) == 2
    assert "cli-reference" in capsys.readouterr().err


# --------------------------------------------------------------------------- the JSON Schemas


def _scenario_files() -> list[Path]:
    files = sorted((ROOT / "configs").rglob("*.yaml")) + sorted((ROOT / "examples").rglob("*.yaml"))
    assert len(files) > 20
    return files


def test_the_json_schemas_accept_every_shipped_scenario():
    jsonschema = pytest.importorskip("jsonschema")
    schemas = {
        kind: json.loads(_text(ROOT / rel))
        for kind, rel in (("simulated", "docs/scenario.schema.json"),
                          ("recorded", "docs/recorded-scenario.schema.json"),
                          ("problem", "docs/problem-scenario.schema.json"))
    }  # fmt: skip
    for schema in schemas.values():
        jsonschema.Draft202012Validator.check_schema(schema)
    for path in _scenario_files():
        data = yaml.safe_load(_text(path))
        kind = "recorded" if "data" in data else "simulated"
        schema = schemas["problem" if data.get("problem", "robot") != "robot" else kind]
        errors = list(jsonschema.Draft202012Validator(schema).iter_errors(data))
        assert errors == [], (path, [e.message for e in errors])


def test_the_json_schema_flags_what_anfekf_run_refuses_and_explains_each_key():
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(_text(ROOT / "docs" / "scenario.schema.json"))
    validator = jsonschema.Draft202012Validator(schema)
    good = {"name": "x", "filters": [{"name": "a", "kind": "anfekf", "window": 20}]}
    assert validator.is_valid(good)
    for bad in ({"name": "x", "runz": 3}, {"name": "x", "runs": 0},
                {"name": "x", "true_noise": {"sigma_v": -1}},
                {"name": "x", "filters": [{"name": "a", "kind": "anfekf", "windw": 20}]},
                {"name": "x", "filters": [{"name": "a", "kind": "no-such-kind"}]}):  # fmt: skip
        assert not validator.is_valid(bad), bad
    # Meanings an editor shows on hover, the docgen MEANINGS included.
    assert schema["properties"]["runs"]["description"].startswith("Monte Carlo runs")
    assert schema["properties"]["name"]["description"].startswith("the result folder's name")
    assert schema["$schema"].endswith("2020-12/schema")


# --------------------------------------------------------------------------- numbers


def test_the_readme_timing_and_machine_are_those_of_results_bench_json():
    bench = json.loads(_text(ROOT / "results" / "bench.json"))
    total = bench["wall_time_paper_scenarios_s"]["total"]
    cpu = bench["machine"]["cpu_model"]
    for path in (README, PAPER_PAGE):
        text = _text(path)
        assert f"{total:.1f} s in all" in text, path
        assert f"({cpu})" in text, path
    performance = _text(ROOT / "docs" / "results" / "performance.md")
    assert f"the project's {bench['machine']['cores']}-core machine ({cpu}," in performance
    assert f"{bench['overhead_ratio']:.2f} x" in performance
    # The README no longer states timings or machines of its own.
    assert "Intel Xeon" not in _text(README)
    assert "47 s in the latest" not in _text(README)


def _report_summary() -> dict[tuple[str, str], dict[str, str]]:
    """The committed reproduction's summary table (results/report/report.md)."""
    text = _text(ROOT / "results" / "report" / "report.md")
    rows = [line for line in text.splitlines() if line.startswith("| ")]
    header = [c.strip() for c in rows[0].strip("|").split("|")]
    assert header[:2] == ["scenario", "filter"], header
    table = {}
    for line in rows[1:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) != len(header) or cells[0].startswith("---"):
            break
        table[(cells[0], cells[1])] = dict(zip(header, cells, strict=True))
    return table


PAPER_SCENARIOS = {"correct noise": "correct", "wrong R": "wrong_r", "wrong Q": "wrong_q",
                   "consistency": "consistency"}  # fmt: skip


def _paper_rows(text: str) -> list[tuple[str, str, list[str]]]:
    """(scenario, filter, cells) of the paper table of a page."""
    start = text.index("| scenario (paper figure) |")
    scenario, out = None, []
    for line in text[start:].splitlines()[2:]:
        if not line.startswith("|"):
            break
        cells = [re.sub(r"\*\*", "", c).strip() for c in line.strip("|").split("|")]
        if cells[0]:
            scenario = next(v for k, v in PAPER_SCENARIOS.items() if cells[0].startswith(k))
        name = re.sub(r"\s*\(.*\)", "", cells[1]).strip()
        out.append((scenario, name, cells[2:]))
    return out


@pytest.mark.parametrize("page", [README, PAPER_PAGE], ids=["README", "results/paper"])
def test_the_paper_table_is_the_committed_reproduction(page):
    summary = _report_summary()
    rows = _paper_rows(_text(page))
    assert len(rows) == 13
    for scenario, name, cells in rows:
        got = summary[(scenario, name)]
        shown = [got["RMSE pos [m]"], got["RMSE heading [deg]"], got["ANEES"],
                 got["NEES in 95 % bounds"]]  # fmt: skip
        assert cells[:4] == shown, (page.name, scenario, name)
        ratios = cells[4:6]
        if ratios[0]:  # the adaptive rows: over the EKF and over the oracle
            assert ratios == [got["RMSE / ekf [95 % CI]"], got["RMSE / oracle [95 % CI]"]], (
                page.name, scenario, name)  # fmt: skip


def test_the_readme_is_short_and_opens_with_its_two_commands():
    lines = _text(README).splitlines()
    assert len(lines) <= MAX_README_LINES, len(lines)
    assert lines[2:6] == [
        "```bash",
        "make reproduce   # sets up .venv, runs the paper's four experiments (50 runs each),"
        " writes the report",
        "make test        # sets up .venv, runs the test suite",
        "```",
    ]


def test_the_readme_links_resolve():
    text = _text(README)
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    assert len(targets) > 15  # the regex finds the links (the README has about twenty)
    for target in targets:
        if not re.match(r"[a-z]+:", target):
            assert (ROOT / target).exists(), target


# --------------------------------------------------------------------------- README commands

CI_SCRIPT = ROOT / ".ci" / "run"
# Commands the README shows that CI does not run as they are, and what covers them.
COVERED = {
    # 50 runs of the four paper scenarios: CI runs the same scenario files at 20 runs through
    # `make gate` (configs/ci, checked identical but for `runs` below) and checks every metric and
    # claim; test_make_reproduce_runs_end_to_end runs `make reproduce`'s two commands at 2 runs.
    "make reproduce": "test_make_reproduce_is_the_gated_scenarios",
    # Python's venv writes activate; `make setup` (run by CI) makes the venv.
    "source .venv/bin/activate": "make setup",
    # CI runs `make test`; the other tiers are the same command with another marker expression.
    "make test-quick": "test_the_test_tiers_differ_from_make_test_only_by_markers",
    "make test-all": "test_the_test_tiers_differ_from_make_test_only_by_markers",
}
CHEAP_ANFEKF = (["--version"], ["-h"], ["kinds"], ["run", "-h"], ["report", "-h"])


def _ci_commands() -> list[str]:
    script = _text(CI_SCRIPT).replace("\\\n", " ")  # continuation lines joined
    lines = [line.strip() for line in script.splitlines()]
    return [line for line in lines if line and not line.startswith("#")]


def _normal(command: str) -> list[str]:
    try:
        words = shlex.split(command)
    except ValueError:  # a shell construct, not a plain command
        return command.split()
    return [w for w in words if w != "--quiet"]


def run_anfekf(args: list[str]) -> None:
    """A cheap `anfekf` command, run in this process: exit 0 and some output."""
    from typer.testing import CliRunner

    from anfekf_bench.cli import app

    done = CliRunner().invoke(app, args)
    assert done.exit_code == 0, (args, done.output)
    assert done.output.strip(), args


def test_the_cheap_anfekf_commands_run():
    for args in CHEAP_ANFEKF:
        run_anfekf(list(args))


def readme_commands() -> list[str]:
    """Every shell command the README shows: each line of its bash blocks and each inline code
    span that is a command (make, anfekf, .venv/bin/..., source), outside HTML comments."""
    text = re.sub(r"<!--.*?-->", "", _text(README), flags=re.S)
    commands = []
    for block in re.findall(r"```(?:bash|sh|shell|console)\n(.*?)```", text, re.S):
        for line in block.splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if line and not line.startswith("#"):
                commands.append(line)
    inline = re.findall(r"`((?:make|anfekf|source|\.venv/bin/\S+) [^`]+)`", text)
    return commands + inline


def test_every_readme_command_runs_in_ci():
    ci = _ci_commands()
    ci_make = {" ".join(_normal(c)[:2]) for c in ci if c.startswith("make ")}
    commands = readme_commands()
    assert "make reproduce" in commands and "make test" in commands
    for command in commands:
        words = _normal(command)
        if command in COVERED:
            continue
        if words[0] == "make":
            assert " ".join(words[:2]) in ci_make, f"{command!r}: not a target .ci/run makes"
        elif words[:3] == [".venv/bin/python", "-m", "pytest"]:
            # `make test` (in CI) runs the whole suite; the README's tiers are marker subsets.
            assert "make test" in ci_make
            assert words[3:] in (["-m", "not slow", "-q"], ["-m", "slow", "-q"]), command
        elif words[0].endswith("/pip"):
            assert any(_normal(c) == words for c in ci), f"{command!r}: not in .ci/run"
        elif words[0] == "anfekf":
            assert words[1:] in [list(c) for c in CHEAP_ANFEKF], f"{command!r}: not covered"
            run_anfekf(words[1:])
        else:
            pytest.fail(f"README command {command!r}: neither run by CI nor covered")


def test_the_test_tiers_differ_from_make_test_only_by_markers():
    """`make test` (CI) leaves out `heavy`, `make test-quick` `slow` (every heavy test is slow
    too), `make test-all` nothing; the same pytest command otherwise."""
    if shutil.which("make") is None:
        pytest.skip("no make")

    def pytest_line(target: str) -> list[str]:
        dry = subprocess.run(["make", "-n", target, "VENV=/nonexistent-venv"], cwd=ROOT,
                             capture_output=True, text=True, timeout=60)  # fmt: skip
        assert dry.returncode == 0, dry.stderr
        (line,) = [ln for ln in dry.stdout.splitlines() if " -m pytest " in ln]
        return shlex.split(line)

    base = pytest_line("test-all")
    assert base[:3] == ["/nonexistent-venv/bin/python", "-m", "pytest"] and "-m" not in base[3:]
    assert pytest_line("test") == [*base, "-m", "not heavy", "--durations=25"]  # CI prints them
    assert pytest_line("test-quick") == [*base, "-m", "not slow"]
    for path in (ROOT / "tests").glob("test_*.py"):
        text = _text(path)
        if "mark.heavy" in text:
            assert "mark.slow" in text, f"{path.name}: a heavy test must be slow too"


def test_make_reproduce_is_the_gated_scenarios():
    """`make reproduce` = `anfekf run configs/` + `anfekf report`; CI's `make gate` runs the same
    four scenario files (configs/ci: the same names, seeds and filters, 20 runs)."""
    if shutil.which("make") is None:
        pytest.skip("no make")
    dry = subprocess.run(["make", "-n", "reproduce", "VENV=/nonexistent-venv"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert dry.returncode == 0, dry.stderr
    assert "/nonexistent-venv/bin/anfekf run configs/ --out results --force" in dry.stdout
    assert "/nonexistent-venv/bin/anfekf report results --out results/report" in dry.stdout
    assert "make gate" in [" ".join(_normal(c)[:2]) for c in _ci_commands()]
    paper = sorted(p.name for p in (ROOT / "configs").glob("*.yaml"))
    assert paper == ["consistency.yaml", "correct.yaml", "wrong_q.yaml", "wrong_r.yaml"]
    for name in paper:
        full = yaml.safe_load(_text(ROOT / "configs" / name))
        gated = yaml.safe_load(_text(ROOT / "configs" / "ci" / name))
        assert {**full, "runs": gated["runs"]} == gated, name


@pytest.mark.slow
@pytest.mark.heavy
def test_make_reproduce_runs_end_to_end(tmp_path):
    """`make reproduce`'s two commands as they are, at 2 runs per scenario."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    out = tmp_path / "results"
    for args in (["run", "configs/", "--out", str(out), "--force", "--runs", "2"],
                 ["report", str(out), "--out", str(out / "report")]):  # fmt: skip
        done = subprocess.run([sys.executable, "-m", "anfekf_bench.entry", *args], cwd=ROOT,
                              env=env, capture_output=True, text=True, timeout=600)  # fmt: skip
        assert done.returncode == 0, (args, done.stderr[-2000:])
    for name in ("consistency", "correct", "wrong_q", "wrong_r"):
        assert (out / name / "manifest.json").is_file(), name
    assert "wrong_r" in (out / "report" / "report.md").read_text(encoding="utf-8")


CPU_TORCH = "pip install torch --index-url https://download.pytorch.org/whl/cpu"


def test_the_cpu_only_pytorch_install_is_what_the_docs_and_make_learned_say():
    """`pip install -e '.[learned]'` alone pulls the CUDA build on Linux (3.2 GB): the docs and
    `make learned`'s hint give the CPU build first."""
    howto = _text(ROOT / "docs" / "how-to" / "learned.md")
    assert f".venv/bin/{CPU_TORCH}" in howto
    assert howto.index(CPU_TORCH) < howto.index(".venv/bin/pip install -e '.[learned]'")
    assert "how-to/learned.md" in _text(ROOT / "docs" / "getting-started.md")
    makefile = _text(ROOT / "Makefile")
    for target in ("learned", "learned-drives"):
        recipe = re.search(rf"^{target}: setup\n((?:\t.*\n)+)", makefile, re.M)
        assert recipe, target
        hint = recipe[1].splitlines()[0]
        assert "torch --index-url https://download.pytorch.org/whl/cpu" in hint, target
        assert hint.index("whl/cpu") < hint.index("[learned]"), target
