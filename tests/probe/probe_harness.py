"""The probe's harness: how a case runs (in this process, through the API or as a real
process) and how its outcome is judged (tracebacks, one-line refusals, data loss by SHA-256, known
answers), the small world and the complete results the cases copy. See probe.py."""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import os
import shutil
import subprocess
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
os.environ.setdefault("MPLBACKEND", "Agg")

from conftest import small_scenario  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

from anfekf_bench import api  # noqa: E402
from anfekf_bench.cli import app  # noqa: E402
from anfekf_bench.config import ScenarioError  # noqa: E402
from anfekf_bench.experiment import PlanError  # noqa: E402
from anfekf_bench.storage import ResultsError  # noqa: E402

RUNNER = CliRunner()
CASE_TIMEOUT_S = 90
API_ERRORS = (ScenarioError, PlanError, ResultsError)  # the API's errors for bad input
# states, not bad input: a complete result without force, a folder another process holds
API_STATES = tuple(getattr(api, n) for n in ("OutputExists", "FolderBusy") if hasattr(api, n))


# ------------------------------------------------------------------------------------------
# Cases and outcomes


@dataclass
class Outcome:
    exit: int | None = None  # exit code (command line) or None (API)
    exception: str | None = None  # an exception's type
    message: str = ""  # the last lines of the output, or the exception's text
    traceback: bool = False
    one_line: bool | None = None  # a refusal: exactly one `error:` line
    data_loss: list[str] = field(default_factory=list)
    wrong: str | None = None  # what was wrong, where the answer is known
    seconds: float = 0.0


@dataclass
class Case:
    family: str
    name: str
    run: Callable[[Path], Outcome]  # called with an empty folder of its own
    listed: bool = False  # one of issue 32's listed cases (else a case nobody listed)


class CaseTimeout(Exception):
    pass


def _alarm(_signum, _frame):
    raise CaseTimeout


def sha_tree(root: Path) -> dict[str, str]:
    """SHA-256 of every file under `root` (lock files aside: their content is a pid)."""
    found = {}
    if not root.exists():
        return found
    for dirpath, _dirs, files in os.walk(root, followlinks=False):
        for f in files:
            p = Path(dirpath) / f
            if f == ".lock" or p.is_symlink() or not p.is_file():
                continue
            with contextlib.suppress(OSError):
                found[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return found


def lost(before: dict, after: dict, allowed: tuple[str, ...] = ()) -> list[str]:
    """Files of `before` changed or removed in `after`, outside the `allowed` prefixes."""
    return sorted(
        k
        for k, v in before.items()
        if after.get(k) != v and not any(k == a or k.startswith(a + "/") for a in allowed)
    )


def judge_output(outcome: Outcome, text: str, debug: bool = False) -> None:
    if "Traceback" in text and not debug:
        outcome.traceback = True
    if outcome.exit == 2 and "Usage:" not in text:  # a refusal (not the help of `anfekf` alone)
        errors = [line for line in text.splitlines() if line.startswith("error:")]
        outcome.one_line = len(errors) == 1
    outcome.message = text.strip()[-400:]


def cli(args: list[str], debug: bool = False) -> Outcome:
    args = [str(a) for a in args]
    res = RUNNER.invoke(app, args, catch_exceptions=True)
    out = Outcome(exit=res.exit_code)
    text = res.output
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        out.traceback = not debug  # uncaught: the real command prints Python's traceback
        out.exception = type(res.exception).__name__
        text += "\n" + "".join(traceback.format_exception(res.exception))[-600:]
    judge_output(out, text, debug)
    if out.traceback:
        out.message = text.strip()[-800:]
    return out


def call_api(
    fn: Callable[[], object], allowed: tuple = API_ERRORS + API_STATES
) -> tuple[Outcome, object]:
    out = Outcome()
    value = None
    try:
        value = fn()
    except allowed as exc:
        out.exception = type(exc).__name__
        out.message = str(exc)[:400]
        out.one_line = "\n" not in str(exc)
    except CaseTimeout:
        raise
    except Exception as exc:  # anything else reaches a user as a traceback
        out.exception = type(exc).__name__
        out.traceback = True
        out.message = "".join(traceback.format_exception(exc))[-800:]
    return out, value


def proc(args: list[str], cwd: Path, timeout: float = 120, **kw) -> tuple[Outcome, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
    p = subprocess.run(
        [sys.executable, "-m", "anfekf_bench.entry", *map(str, args)],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        **kw,
    )
    out = Outcome(exit=p.returncode)
    judge_output(out, p.stdout + p.stderr, "--debug" in args)
    return out, p.stdout + p.stderr


# ------------------------------------------------------------------------------------------
# The small world: one scenario, two filters, a ~20 m route (a run takes about 0.1 s)

TINY_WORLD = {"landmarks": [[10, 8], [25, -6], [15, -10]], "waypoints": [[20, 0]]}


def tiny(**overrides) -> dict:
    doc = small_scenario(
        runs=1,
        jobs=1,
        world=copy.deepcopy(TINY_WORLD),
        filters=[{"name": "ekf", "kind": "ekf"}, {"name": "ekf-oracle", "kind": "ekf-oracle"}],
    )
    doc.update(overrides)
    return doc


def write_yaml(path: Path, doc) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False, allow_unicode=True), encoding="utf-8")
    return path


class Templates:
    """Complete results made once, copied into each case's folder."""

    def __init__(self, root: Path) -> None:
        self.root = root
        root.mkdir(parents=True)
        claim = {"filter": "ekf-oracle", "vs": "ekf", "metric": "rmse_pos", "at_most": 100.0}
        self.small_doc = tiny(runs=2, claims=[claim])
        write_yaml(root / "small.yaml", self.small_doc)
        write_yaml(root / "sib.yaml", tiny(name="sib"))
        for name in ("small", "sib"):
            res = cli(["run", root / f"{name}.yaml", "--out", root / "out"])
            assert res.exit == 0, res.message
        self.out = root / "out"
        res = cli(["check", self.out, "--baseline", root / "baseline.json", "--update"])
        assert res.exit == 0, res.message
        self.baseline = json.loads((root / "baseline.json").read_text())

    def results(self, where: Path, names=("small", "sib")) -> Path:
        where.mkdir(parents=True, exist_ok=True)
        for n in names:
            shutil.copytree(self.out / n, where / n)
        return where


T: Templates | None = None  # the complete results the cases copy: set by probe.main()


def run_count(folder: Path) -> int | None:
    import pandas as pd

    try:
        return int(pd.read_parquet(folder / "runs.parquet")["run"].nunique())
    except Exception:
        return None


def run_case_cli(
    d: Path,
    doc_or_path,
    extra=(),
    expect: str | None = None,
    runs=None,
    force=False,
    name=None,
    prepare=True,
) -> Outcome:
    """`anfekf run` of a scenario into d/out (holding a complete sibling result), then the
    data-loss and run-count checks."""
    out_dir = d / "out"
    if prepare:
        T.results(out_dir, ("sib",))
    if isinstance(doc_or_path, (dict, list, str, int, float)) or doc_or_path is None:
        path = d / "s.yaml"
        if isinstance(doc_or_path, str) and doc_or_path.startswith("RAW:"):
            path.write_bytes(doc_or_path[4:].encode("utf-8", "surrogatepass"))
        else:
            write_yaml(path, doc_or_path)
    else:
        path = doc_or_path
    before = sha_tree(out_dir)
    args = ["run", path, "--out", out_dir, *extra] + (["--force"] if force else [])
    out = cli(args, debug="--debug" in extra)
    own = name or (doc_or_path.get("name") if isinstance(doc_or_path, dict) else None)
    out.data_loss = lost(before, sha_tree(out_dir), (own,) if force and own else ())
    if expect == "ok" and out.exit != 0:
        out.wrong = "refused a valid case"
    if expect == "refuse" and out.exit == 0:
        out.wrong = "accepted an invalid case"
    if out.exit == 0 and own and isinstance(doc_or_path, dict) and (out_dir / own).is_dir():
        want = runs if runs is not None else doc_or_path.get("runs")
        got = run_count(out_dir / own)
        if (
            isinstance(want, int)
            and got is not None
            and got != want
            and not doc_or_path.get("sweep")
        ):
            out.wrong = f"runs: wanted {want}, the result holds {got}"
    return out
