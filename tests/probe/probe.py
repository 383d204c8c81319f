"""The hardening probe (issue 32): hundreds of generated cases of bad input against the command
line, the Python API and the files they read, counting data loss, tracebacks and wrong results.

    PYTHONPATH=$PWD .venv/bin/python tests/probe/probe.py --out /tmp/probe-report.json

Not a pytest module (its name does not match `test_*.py`): a standalone script, run on demand
(docs/HARDENING.md, "The probe"). Each case records its exit code or exception, whether a
traceback was shown, whether a refusal was one `error:` line, a SHA-256 of every file of the
output folders before and after (data loss: a file of a previous complete result changed or
removed, other than the forced scenario's own folder) and, where the answer is known, whether
the outcome was right (a run's run count, a refusal of an invalid value, `check` on an inverted
interval). Most cases run in this process (typer's CliRunner, the API); a few dozen run as real
processes where the process boundary matters (signals, /dev/full, closed streams).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from collections import Counter
from pathlib import Path

import probe_harness as h
from probe_harness import CASE_TIMEOUT_S, Case, CaseTimeout, Outcome, Templates, _alarm
from probe_inputs import (
    filters_cases,
    flag_cases,
    recorded_cases,
    scenario_cases,
    schedule_cases,
)
from probe_outputs import (
    api_cases,
    baseline_cases,
    init_cases,
    output_cases,
    process_cases,
    tamper_cases,
)

# ------------------------------------------------------------------------------------------


def all_cases() -> list[Case]:
    return (
        scenario_cases()
        + schedule_cases()
        + filters_cases()
        + recorded_cases()
        + flag_cases()
        + api_cases()
        + output_cases()
        + tamper_cases()
        + baseline_cases()
        + init_cases()
        + process_cases()
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("probe-report.json"))
    parser.add_argument("--family", action="append", help="run only these families")
    parser.add_argument("--match", help="run only cases whose name contains this")
    args = parser.parse_args()
    started = time.monotonic()
    work = Path(tempfile.mkdtemp(prefix="anfekf-probe-"))
    h.T = Templates(work / "templates")
    cases = all_cases()
    if args.family:
        cases = [c for c in cases if c.family in args.family]
    if args.match:
        cases = [c for c in cases if args.match in c.name]
    signal.signal(signal.SIGALRM, _alarm)
    records = []
    for n, case in enumerate(cases):
        d = work / f"case-{n:04d}"
        d.mkdir()
        t0 = time.monotonic()
        cwd = os.getcwd()
        signal.alarm(CASE_TIMEOUT_S)
        try:
            outcome = case.run(d)
        except CaseTimeout:
            outcome = Outcome(wrong=f"no answer within {CASE_TIMEOUT_S} s")
        except Exception as exc:  # the probe's own failure: shown, counted apart
            outcome = Outcome(
                exception="PROBE:" + type(exc).__name__,
                message="".join(traceback.format_exception(exc))[-800:],
            )
        finally:
            signal.alarm(0)
            os.chdir(cwd)
        outcome.seconds = round(time.monotonic() - t0, 2)
        records.append(
            {"family": case.family, "case": case.name, "listed": case.listed, **outcome.__dict__}
        )
        flag = (
            ("LOSS " if outcome.data_loss else "")
            + ("TRACEBACK " if outcome.traceback else "")
            + ("WRONG " if outcome.wrong else "")
            + ("PROBE " if (outcome.exception or "").startswith("PROBE") else "")
        )
        if flag:
            why = f"{outcome.wrong or ''} {outcome.message[-300:]!r}"
            print(f"{flag}{case.family}: {case.name!r}: {why}", flush=True)
        subprocess.run(["chmod", "-R", "u+rwx", str(d)], check=False, capture_output=True)
        shutil.rmtree(d, ignore_errors=True)
    totals = {
        "cases": len(records),
        "listed": sum(r["listed"] for r in records),
        "unlisted": sum(not r["listed"] for r in records),
        "per_family": dict(Counter(r["family"] for r in records)),
        "data_loss": sum(bool(r["data_loss"]) for r in records),
        "tracebacks": sum(r["traceback"] for r in records),
        "wrong_results": sum(bool(r["wrong"]) for r in records),
        "probe_errors": sum((r["exception"] or "").startswith("PROBE") for r in records),
        "refusals_not_one_line": sum(r["one_line"] is False for r in records),
        "seconds": round(time.monotonic() - started, 1),
    }
    args.out.write_text(json.dumps({"totals": totals, "cases": records}, indent=1, default=str))
    shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(totals, indent=1))
    bad = (
        totals["data_loss"]
        + totals["tracebacks"]
        + totals["wrong_results"]
        + totals["probe_errors"]
    )
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
