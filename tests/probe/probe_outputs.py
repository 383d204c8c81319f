"""Probe cases on the output side: the Python API, output folders, tampered result files,
baselines for `check`, `init` file names, and real processes (signals, full or closed streams)."""

from __future__ import annotations

import contextlib
import copy
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import probe_harness as h
import yaml
from probe_harness import (
    API_ERRORS,
    ROOT,
    Case,
    Outcome,
    api,
    call_api,
    cli,
    judge_output,
    lost,
    proc,
    run_count,
    sha_tree,
    tiny,
    write_yaml,
)

# ------------------------------------------------------------------------------------------
# Family 4: the Python API


class Weird:
    """A path-like object whose path is not text (os.fspath raises TypeError)."""

    def __fspath__(self):
        return 3


def api_cases() -> list[Case]:
    import numpy as np

    cases = []
    good = lambda: tiny(name="small")  # noqa: E731
    arg_values = {
        "runs": [True, False, 2.5, -1, 0, "2", 10**6, np.int64(2), np.float64(2.0), [2], 2],
        "seed": [-1, 2**64, 1.5, "7", True, np.uint64(3), 3],
        "jobs": [0, -1, 10**6, 1.0, "2", 1],
        "engine": ["bogus", "", 3, None, "fast"],
        "backend": ["bogus", 0, "local"],
        "scheduler": [3, "", "tcp://127.0.0.1:1"],
        "force": ["no", 1, 0, None, True],
        "on_result": [3, "print", lambda r: None],
    }
    for arg, values in arg_values.items():
        for v in values:
            okay = (arg, repr(v)) in {
                ("runs", "2"),
                ("runs", "np.int64(2)"),
                ("seed", "3"),
                ("jobs", "1"),
                ("engine", "'fast'"),
                ("engine", "None"),
                ("backend", "'local'"),
                ("force", "True"),
                ("force", "None"),
                ("seed", "np.uint64(3)"),
            } or (arg == "on_result" and callable(v))
            if arg == "runs" and isinstance(v, np.integer):
                okay = True

            def run(d, arg=arg, v=v, okay=okay):
                h.T.results(d / "out", ("sib",) if okay and arg != "force" else ("small", "sib"))
                before = sha_tree(d / "out")
                out, res = call_api(lambda: api.run(good(), out=d / "out", **{arg: v}))
                forced = arg == "force" and v is True
                out.data_loss = lost(before, sha_tree(d / "out"), ("small",) if forced else ())
                if res is None and okay and (arg != "force" or v is True):
                    out.wrong = f"refused {arg}={v!r}"
                if res is not None and not okay and arg != "force":
                    out.wrong = f"accepted {arg}={v!r}"
                if res is not None and arg == "runs":
                    want = (
                        int(v)
                        if isinstance(v, (int, np.integer)) and not isinstance(v, bool)
                        else None
                    )
                    if want is not None and run_count(res.folder) != want:
                        out.wrong = f"runs {run_count(res.folder)} != {want}"
                if arg == "force" and v is not True and res is not None and v not in (None,):
                    out.wrong = f"force={v!r} accepted"
                return out

            listed = (arg, repr(v)) in {
                ("runs", "True"),
                ("engine", "'bogus'"),
                ("force", "'no'"),
                ("runs", "-1"),
                ("runs", "2.5"),
                ("seed", "-1"),
            }
            cases.append(Case("api", f"run {arg}={v!r}", run, listed))
    # the experiment and out arguments
    for label, exp, out_name in [
        ("exp-int", 3, "out"),
        ("exp-none", None, "out"),
        ("exp-list", [1], "out"),
        ("exp-missing-file", "/nonexistent.yaml", "out"),
        ("exp-bytes", b"s.yaml", "out"),
        ("exp-weird-pathlike", Weird(), "out"),
        ("exp-dict-bad", {"name": 3}, "out"),
        ("exp-dict-empty", {}, "out"),
        ("out-int", "GOOD", 3),
        ("out-nul", "GOOD", "a\x00b"),
        ("out-file", "GOOD", "FILE"),
        ("out-bytes", "GOOD", b"out"),
        ("out-result", "GOOD", "RESULT"),
        ("out-runstore", "GOOD", "RUNSTORE"),
        ("out-weird", "GOOD", Weird()),
        ("out-empty", "GOOD", ""),
    ]:

        def run(d, exp=exp, out_name=out_name):
            h.T.results(d / "out", ("small", "sib"))
            (d / "file").write_text("x")
            (d / "out/sib/.runs").mkdir(exist_ok=True)
            o = (
                {
                    "FILE": d / "file",
                    "RESULT": d / "out/sib",
                    "RUNSTORE": d / "out/sib/.runs",
                    "out": d / "out",
                }.get(out_name, out_name)
                if isinstance(out_name, str)
                else out_name
            )
            e = tiny(name="small") if exp == "GOOD" else exp
            before = sha_tree(d / "out")
            cwd = os.getcwd()
            os.chdir(d)
            try:
                out, _ = call_api(lambda: api.run(e, out=o))
            finally:
                os.chdir(cwd)
            out.data_loss = lost(before, sha_tree(d / "out"))
            if out_name in ("RESULT", "RUNSTORE") and out.exception is None:
                out.wrong = "an output folder inside another result was accepted"
            return out

        cases.append(Case("api", f"run {label}", run, label == "out-runstore"))
    # load, open_result, Result, report and the tables
    for label, fn in {
        "load-int": lambda d: api.load(3),
        "load-none": lambda d: api.load(None),
        "load-base-int": lambda d: api.load(tiny(), base=3),
        "load-base-nul": lambda d: api.load(tiny(), base="\x00"),
        "load-dir": lambda d: api.load(d),
        "load-dict-list-world": lambda d: api.load(tiny(world=[1])),
        "load-ok": lambda d: api.load(tiny()),
        "load-path-ok": lambda d: api.load(write_yaml(d / "s.yaml", tiny())),
        "load-recorded-dict": lambda d: api.load(
            yaml.safe_load((ROOT / "configs/real/mrclam-d9.yaml").read_text())
        ),
        "open-int": lambda d: api.open_result(3),
        "open-missing": lambda d: api.open_result(d / "x"),
        "open-file": lambda d: api.open_result(d / "f"),
        "open-parent": lambda d: api.open_result(d / "res"),
        "open-ok-summary": lambda d: api.open_result(d / "res/small").summary(),
        "open-ok-runs": lambda d: api.open_result(d / "res/small").runs(),
        "open-ok-steps": lambda d: api.open_result(d / "res/small").steps(),
        "open-ok-comparisons": lambda d: api.open_result(d / "res/small").comparisons(),
        "open-ok-claims": lambda d: api.open_result(d / "res/small").claims(),
        "open-ok-manifest": lambda d: api.open_result(d / "res/small").manifest(),
        "open-empty-dir": lambda d: api.open_result(d / "e").summary(),
        "result-int": lambda d: api.Result(3),
        "result-none": lambda d: api.Result(None),
        "result-missing-summary": lambda d: api.Result(d / "x").summary(),
        "result-missing-manifest": lambda d: api.Result(d / "x").manifest(),
        "result-claims-missing": lambda d: api.Result(d / "e").claims(),
        "report-str": lambda d: api.report(str(d / "res/small"), out=d / "rep"),
        "report-empty": lambda d: api.report([], out=d / "rep"),
        "report-int": lambda d: api.report(3, out=d / "rep"),
        "report-list-int": lambda d: api.report([3], out=d / "rep"),
        "report-out-int": lambda d: api.report(d / "res/small", out=3),
        "report-out-file": lambda d: api.report(d / "res/small", out=d / "f"),
        "report-missing": lambda d: api.report(d / "nope", out=d / "rep"),
        "report-generator": lambda d: api.report((p for p in [d / "res/small"]), out=d / "rep"),
        "report-dict": lambda d: api.report({"a": 1}, out=d / "rep"),
        "report-out-nul": lambda d: api.report(d / "res/small", out="a\x00"),
    }.items():

        def run(d, fn=fn, label=label):
            h.T.results(d / "res")
            (d / "f").write_text("x")
            (d / "e").mkdir()
            before = sha_tree(d / "res")
            out, value = call_api(lambda: fn(d), API_ERRORS + (FileNotFoundError,))
            out.data_loss = lost(before, sha_tree(d / "res"))
            if label.startswith("open-ok") and out.exception is not None:
                out.wrong = "a good result was refused"
            if label == "open-ok-runs" and value is not None and value["run"].nunique() != 2:
                out.wrong = "wrong run count"
            return out

        cases.append(Case("api", label, run, label in ("report-str",)))
    return cases


# ------------------------------------------------------------------------------------------
# Family 5: output folders


def output_cases() -> list[Case]:
    def file_at(p: Path, text="x") -> Path:
        p.write_text(text)
        return p

    def mkdir(p: Path) -> Path:
        p.mkdir(parents=True)
        return p

    layouts = {
        "inside-runstore": lambda d: d / "out/sib/.runs",
        "inside-runstore-deep": lambda d: d / "out/sib/.runs/a/b",
        "inside-result": lambda d: d / "out/sib",
        "inside-result-sub": lambda d: d / "out/sib/x",
        "symlink-to-result": lambda d: (d / "link").symlink_to(d / "out/sib") or d / "link",
        "symlink-to-runstore": lambda d: (d / "l2").symlink_to(d / "out/sib/.runs") or d / "l2",
        "a-file": lambda d: file_at(d / "file"),
        "under-a-file": lambda d: file_at(d / "file") / "sub",
        "fifo": lambda d: os.mkfifo(d / "fifo") or d / "fifo",
        "read-only": lambda d: (d / "ro").mkdir() or os.chmod(d / "ro", 0o555) or d / "ro",
        "dev-null": lambda d: Path("/dev/null"),
        "proc": lambda d: Path("/proc/self"),
        "dangling-symlink": lambda d: (d / "dl").symlink_to(d / "nowhere") or d / "dl",
        "symlink-loop": lambda d: (d / "loop").symlink_to(d / "loop") or d / "loop",
        "dot": lambda d: Path("."),
        "same-out": lambda d: d / "out",
        "target-is-file": lambda d: file_at(mkdir(d / "o2") / "small").parent,
        "target-symlink-to-sib": lambda d: (
            (d / "o3").mkdir() or (d / "o3/small").symlink_to(d / "out/sib") or d / "o3"
        ),
        "target-foreign-dir": lambda d: file_at(mkdir(d / "o4/small") / "mine.txt").parent.parent,
        "target-holds-nested-result": lambda d: (
            shutil.copytree(h.T.out / "sib", d / "o5/small/.runs/sib") and d / "o5"
        ),
        "sweep-cell-root": lambda d: d / "out/sib/cells",
        "in-report-folder": lambda d: file_at(mkdir(d / "rep") / "report.md").parent,
        "long-path": lambda d: d / ("p" * 250) / ("q" * 250),
        "too-long-name": lambda d: d / ("p" * 300),
        "esc-name": lambda d: d / "\x1b[31mout",
        "newline-name": lambda d: d / "a\nb",
        "unicode-name": lambda d: d / "résultats😀",
    }
    cases = []
    for label, make in layouts.items():
        for force in (False, True):

            def run(d, make=make, force=force, label=label):
                h.T.results(d / "out", ("small", "sib"))
                write_yaml(d / "s.yaml", tiny(name="small"))
                cwd = os.getcwd()
                os.chdir(d)
                try:
                    target = make(d)
                    before = sha_tree(d)
                    out = cli(
                        ["run", d / "s.yaml", "--out", target] + (["--force"] if force else [])
                    )
                    after = sha_tree(d)
                finally:
                    os.chdir(cwd)
                    with contextlib.suppress(OSError):
                        os.chmod(d / "ro", 0o755)
                own = []
                if force:
                    with contextlib.suppress(OSError, ValueError):
                        t = Path(os.path.realpath(d / target / "small"))
                        own = [str(t.relative_to(Path(os.path.realpath(d))))]
                out.data_loss = lost(before, after, tuple(own))
                if (
                    label.startswith("inside")
                    or label.startswith("symlink-to")
                    or label == "target-holds-nested-result"
                ):
                    if out.exit == 0:
                        out.wrong = "an output folder inside another result was accepted"
                return out

            cases.append(
                Case(
                    "outputs",
                    f"{label}{' --force' if force else ''}",
                    run,
                    label == "inside-runstore",
                )
            )
    return cases


# ------------------------------------------------------------------------------------------
# Family 6: tampered result files (read by report, check and the API)


def manifest_edits() -> dict[str, Callable[[dict], object]]:
    def put(key, value):
        def edit(m):
            m[key] = value
            return m

        return edit

    def put_in(path, value):
        def edit(m):
            node = m
            for k in path[:-1]:
                node = node[k]
            node[path[-1]] = value
            return m

        return edit

    edits = {}
    for key in (
        "runs",
        "seed",
        "jobs",
        "engine",
        "format",
        "fingerprint",
        "filters",
        "scenario",
        "world",
        "training",
        "resumed_runs",
        "versions",
        "engines",
        "backend",
    ):
        edits[f"{key}-missing"] = lambda m, key=key: {k: v for k, v in m.items() if k != key}
        for label, value in [
            ("str", "x"),
            ("neg", -1),
            ("huge", 10**400 if key == "runs" else 1e308),
            ("null", None),
            ("list", [1]),
            ("bool", True),
        ]:
            edits[f"{key}-{label}"] = put(key, value)
    edits["scenario-name-other"] = put_in(["scenario", "name"], "other")
    edits["scenario-name-esc"] = put_in(["scenario", "name"], "\x1b[2J")
    edits["scenario-name-slash"] = put_in(["scenario", "name"], "../../x")
    edits["scenario-desc-surrogate"] = put_in(["scenario", "description"], "\udcff")
    edits["scenario-filters-empty"] = put_in(["scenario", "filters"], [])
    edits["landmarks-1e308"] = put_in(["world", "landmarks"], [[1e308, 1e308]])
    edits["landmarks-nan"] = put_in(["world", "landmarks"], [["NaN", 1]])
    edits["landmarks-empty"] = put_in(["world", "landmarks"], [])
    edits["waypoints-3d"] = put_in(["world", "waypoints"], [[1, 2, 3]])
    edits["top-list"] = lambda m: [m]
    edits["top-null"] = lambda m: None
    edits["top-empty"] = lambda m: {}
    return edits


def tamper_cases() -> list[Case]:
    cases = []
    readers = {
        "report": lambda d, res: cli(["report", res, "--out", d / "rep"]),
        "check": lambda d, res: cli(["check", res]),
        "api": lambda d, res: call_api(lambda: api.open_result(res / "small").summary())[0],
    }
    for label, edit in manifest_edits().items():
        for reader_name, reader in readers.items():
            if reader_name == "report" and not any(
                label.startswith(k)
                for k in ("runs", "scenario", "landmarks", "top", "format", "world")
            ):
                continue  # report is slow: the manifest keys it draws from

            def run(d, edit=edit, reader=reader):
                res = h.T.results(d / "res")
                m = json.loads((res / "small/manifest.json").read_text())
                text = json.dumps(edit(m), ensure_ascii=True)
                (res / "small/manifest.json").write_text(text)
                before = sha_tree(res)
                out = reader(d, res)
                out.data_loss = lost(before, sha_tree(res))
                # the template's one claim holds: a damaged manifest is read (exit 0) or refused
                # (exit 2), never a gate that fails on what it could not read
                if out.exit == 1:
                    out.wrong = "check failed the gate on a damaged manifest instead of refusing it"
                return out

            cases.append(
                Case(
                    "tamper",
                    f"manifest {label} / {reader_name}",
                    run,
                    label in ("landmarks-1e308", "scenario-desc-surrogate"),
                )
            )
    garbage = {
        "garbage": os.urandom(500),
        "empty": b"",
        "truncated": None,
        "json": b"{}",
        "csv": b"a,b\n1,2\n",
        "other-table": "OTHER",
    }
    for table in (
        "runs.parquet",
        "summary.parquet",
        "comparisons.parquet",
        "steps.parquet",
        "claims.json",
        "summary.json",
    ):
        for label, content in garbage.items():
            for reader_name in (
                ("check", "api", "report")
                if table in ("runs.parquet", "summary.parquet")
                else ("check", "api")
            ):

                def run(d, table=table, content=content, reader_name=reader_name):
                    res = h.T.results(d / "res")
                    p = res / "small" / table
                    if content is None:
                        p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
                    elif content == "OTHER":
                        other = "runs.parquet" if table != "runs.parquet" else "summary.parquet"
                        if table.endswith(".json"):
                            other = "manifest.json"
                        shutil.copy(res / "small" / other, p)
                    else:
                        p.write_bytes(content)
                    before = sha_tree(res)
                    if reader_name == "api":
                        name = {
                            "runs.parquet": "runs",
                            "summary.parquet": "summary",
                            "comparisons.parquet": "comparisons",
                            "steps.parquet": "steps",
                            "claims.json": "claims",
                            "summary.json": "manifest",
                        }[table]
                        out = call_api(lambda: getattr(api.open_result(res / "small"), name)())[0]
                    else:
                        out = readers[reader_name](d, res)
                    out.data_loss = lost(before, sha_tree(res))
                    return out

                cases.append(Case("tamper", f"{table} {label} / {reader_name}", run))

    # the run store of a batch in progress (a callback stopped it after its first run), its
    # files and its fit cache edited, then resumed and forced
    class Stop(Exception):
        pass

    def stop(_record):
        raise Stop

    store_edits = [
        "garbage",
        "empty",
        "truncated",
        "json-list",
        "symlink",
        "dir",
        "fifo",
        "huge-index",
        "other-name",
        "readonly",
        "fit-garbage",
        "fit-sigma-neg",
        "fit-sigma-text",
        "fit-missing-key",
        "fit-list",
        "fit-nonutf8",
        "fit-hash",
        "fit-nan",
        "fit-empty",
        "fit-symlink",
        "fit-dir",
        "stamp-garbage",
    ]
    for label in store_edits:

        def run(d, label=label):
            doc = tiny(
                name="small",
                runs=3,
                training={"runs": 2},
                filters=[{"name": "ekf", "kind": "ekf"}, {"name": "ml", "kind": "ekf-ml"}],
            )
            write_yaml(d / "s.yaml", doc)
            h.T.results(d / "out", ("sib",))
            with contextlib.suppress(Stop):
                api.run(d / "s.yaml", out=d / "out", on_result=stop)
            store = d / "out/small/.runs"
            runs_files = sorted(store.glob("run-*"))
            fits = sorted(store.glob("fit-*.json"))
            others = sorted(p for p in store.iterdir() if p not in runs_files + fits)
            if not runs_files or not fits:
                return Outcome(
                    exit=None, wrong=f"probe setup: no run store ({list(store.iterdir())})"
                )
            p = (
                fits[0]
                if label.startswith("fit-")
                else (others[0] if label.startswith("stamp") and others else runs_files[0])
            )
            fit = json.loads(fits[0].read_text())
            if label in ("garbage", "fit-garbage", "stamp-garbage"):
                p.write_bytes(os.urandom(100))
            elif label in ("empty", "fit-empty"):
                p.write_bytes(b"")
            elif label == "truncated":
                p.write_bytes(p.read_bytes()[:10])
            elif label in ("json-list", "fit-list"):
                p.write_text("[1, 2]")
            elif label in ("symlink", "fit-symlink"):
                p.unlink()
                p.symlink_to("/etc/passwd")
            elif label in ("dir", "fit-dir"):
                p.unlink()
                p.mkdir()
            elif label == "fifo":
                p.unlink()
                os.mkfifo(p)
            elif label == "huge-index":
                (store / ("run-" + "9" * 200 + ".parquet")).write_text("x")
            elif label == "other-name":
                (store / "run-00001-other.parquet").write_text("x")
            elif label == "readonly":
                os.chmod(p, 0o444)
            elif label == "fit-nonutf8":
                p.write_bytes(b"\xff\xfe" + p.read_bytes())
            elif label.startswith("fit-"):
                text = json.dumps(fit)

                def edit_sigma(node, value):
                    if isinstance(node, dict):
                        for k in list(node):
                            if k.startswith("sigma"):
                                if value == "DEL":
                                    del node[k]
                                else:
                                    node[k] = value
                                return True
                            if edit_sigma(node[k], value):
                                return True
                    return False

                if label == "fit-hash":
                    text = text.replace(text[-20:-10], "0" * 10)
                else:
                    value = {
                        "fit-sigma-neg": -1.0,
                        "fit-sigma-text": "x",
                        "fit-missing-key": "DEL",
                        "fit-nan": float("nan"),
                    }[label]
                    edit_sigma(fit, value)
                    text = json.dumps(fit)
                p.write_text(text)
            before = sha_tree(d / "out/sib")
            out = cli(["run", d / "s.yaml", "--out", d / "out"])
            if out.exit == 0 and run_count(d / "out/small") != 3:
                out.wrong = f"resumed: {run_count(d / 'out/small')} runs, not 3"
            out2 = cli(["run", d / "s.yaml", "--out", d / "out", "--force"])
            out.data_loss = lost(before, sha_tree(d / "out/sib"))
            out.traceback = out.traceback or out2.traceback
            out.message += " | force: " + out2.message[-300:]
            if out2.exit == 0 and run_count(d / "out/small") != 3:
                out.wrong = "forced rerun: wrong run count"
            return out

        cases.append(Case("tamper", f"run store {label}, resumed", run, label.startswith("fit-")))
    return cases


# ------------------------------------------------------------------------------------------
# Family 7: baselines for `check`, and edited comparisons (known answers)


def baseline_cases() -> list[Case]:
    def edit_first_metric(b, value):
        scen = next(iter(b["scenarios"].values()))
        filt = next(iter(scen["filters"].values())) if "filters" in scen else None
        target = filt if isinstance(filt, dict) else scen
        for k in list(target):
            if isinstance(target[k], (int, float)) and not isinstance(target[k], bool):
                target[k] = value
                break
        return b

    variants: dict[str, Callable[[dict], object]] = {
        "unchanged": lambda b: b,
        "empty-object": lambda b: {},
        "list": lambda b: [b],
        "null": lambda b: None,
        "scenarios-list": lambda b: dict(b, scenarios=[]),
        "scenarios-empty": lambda b: dict(b, scenarios={}),
        "metric-huge": lambda b: edit_first_metric(b, 1e308),
        "metric-neg": lambda b: edit_first_metric(b, -1e308),
        "metric-text": lambda b: edit_first_metric(b, "x"),
        "metric-null": lambda b: edit_first_metric(b, None),
        "metric-bool": lambda b: edit_first_metric(b, True),
        "metric-bigint": lambda b: edit_first_metric(b, 10**400),
        "esc-scenario": lambda b: dict(
            b, scenarios={"\x1b[2Jx" + k: v for k, v in b["scenarios"].items()}
        ),
        "surrogate-scenario": lambda b: dict(
            b, scenarios={"\udcff" + k: v for k, v in b["scenarios"].items()}
        ),
        "tolerances-neg": lambda b: dict(b, tolerances={"rmse_pos": {"relative": -1}}),
        "tolerances-text": lambda b: dict(b, tolerances="x"),
        "tolerances-unknown": lambda b: dict(b, tolerances={"bogus": {"relative": 1}}),
        "tolerances-huge": lambda b: dict(b, tolerances={"rmse_pos": {"absolute": 1e308}}),
        "tolerances-nan": lambda b: dict(b, tolerances={"rmse_pos": {"relative": float("nan")}}),
        "format-other": lambda b: dict(b, format="other"),
        "extra-key": lambda b: dict(b, bogus=1),
        "many-scenarios": lambda b: dict(
            b, scenarios={f"s{i}": v for i in range(2000) for v in b["scenarios"].values()}
        ),
    }
    cases = []
    for label, edit in variants.items():

        def run(d, edit=edit, label=label):
            res = h.T.results(d / "res")
            b = edit(copy.deepcopy(h.T.baseline))
            raw = json.dumps(b, allow_nan=True, ensure_ascii=True)
            (d / "b.json").write_text(raw)
            before = sha_tree(res)
            out = cli(["check", res, "--baseline", d / "b.json"])
            out.data_loss = lost(before, sha_tree(res))
            if label == "unchanged" and out.exit != 0:
                out.wrong = "the same results fail their own baseline"
            return out

        cases.append(Case("baseline", label, run, label == "esc-scenario"))
    for label, raw in {
        "not-json": b"{",
        "empty": b"",
        "binary": os.urandom(200),
        "nonutf8": b'{"\xff": 1}',
        "dup-keys": None,
        "deep": b"[" * 100000 + b"]" * 100000,
    }.items():

        def run(d, raw=raw):
            res = h.T.results(d / "res")
            if raw is None:
                text = json.dumps(h.T.baseline)
                raw = (text[:-1] + ', "scenarios": {}}').encode()
            (d / "b.json").write_bytes(raw)
            return cli(["check", res, "--baseline", d / "b.json"])

        cases.append(Case("baseline", f"file {label}", run))
    # comparisons and claims edited: check must never say "holds" on an invalid interval
    comp_edits = {
        "inverted": lambda c: c.assign(lo=c["hi"] + 1.0),
        "estimate-out": lambda c: c.assign(estimate=c["hi"] + 5),
        "lo-nan-hi-num": lambda c: c.assign(lo=float("nan")),
        "inf": lambda c: c.assign(hi=float("inf")),
        "dup-failing-row": lambda c: __import__("pandas").concat(
            [c, c.assign(estimate=1e3, lo=1e3, hi=1e3)]
        ),
        "all-nan": lambda c: c.assign(lo=float("nan"), hi=float("nan"), estimate=float("nan")),
        "empty": lambda c: c.iloc[0:0],
        "text-column": lambda c: c.assign(lo="x"),
        "missing-column": lambda c: c.drop(columns=["lo"]),
    }
    for label, edit in comp_edits.items():

        def run(d, edit=edit, label=label):
            import pandas as pd

            res = h.T.results(d / "res")
            p = res / "small/comparisons.parquet"
            c = pd.read_parquet(p)
            with contextlib.suppress(Exception):
                edit(c).to_parquet(p)
            out = cli(["check", res])
            if (
                label in ("inverted", "estimate-out", "dup-failing-row", "lo-nan-hi-num", "inf")
                and out.exit == 0
            ):
                out.wrong = f"check passed on an invalid comparisons table ({label})"
            return out

        cases.append(
            Case("baseline", f"comparisons {label}", run, label in ("inverted", "estimate-out"))
        )
    for label, edit in {
        "claim-held-flip": lambda c: [dict(r, holds=not r.get("holds")) for r in c],
        "claim-lo-inverted": lambda c: [dict(r, lo=9.0, hi=0.1) for r in c],
        "claim-dup": lambda c: c + c,
        "claim-not-list": lambda c: {"a": 1},
        "claim-text": lambda c: "x",
        "claim-empty": lambda c: [],
        "claim-dup-failing": lambda c: c + [dict(r, estimate=1e3, lo=1e3, hi=1e3) for r in c],
    }.items():

        def run(d, edit=edit, label=label):
            res = h.T.results(d / "res")
            p = res / "small/claims.json"
            p.write_text(json.dumps(edit(json.loads(p.read_text()))))
            out = cli(["check", res])
            if label in ("claim-lo-inverted", "claim-dup-failing") and out.exit == 0:
                out.wrong = f"check passed on invalid claims ({label})"
            return out

        cases.append(Case("baseline", label, run))
    return cases


# ------------------------------------------------------------------------------------------
# Family 8: `init` file names (the starter must be one `run` accepts)


def init_cases() -> list[Case]:
    names = [
        "report",
        "baselines",
        "ci-gate",
        "_x",
        ".hidden",
        "-dash",
        "café",
        "日本語",
        "a" * 64,
        "a" * 65,
        "a" * 200,
        "1",
        "0x1",
        "1e3",
        "null",
        "true",
        "~",
        ".inf",
        "[a]",
        "{a}",
        "a:b",
        "a#b",
        "a b",
        "a\tb",
        "a\nb",
        "\x1b[31m",
        "a'b",
        'a"b',
        "%",
        "@",
        "*",
        "&a",
        "!tag",
        "-",
        "..",
        "steps.parquet",
        "manifest.json",
        ".runs",
        "cells",
        "summary",
        "CON",
        "nul",
        "x" * 251,
        "😀",
        "Ω",
        "a.b.c",
        "A",
        "results",
        "report.md",
        "sweep",
        "\u202e",
        "\u0301a",
        "ℌ",
        "ß",
        "İ",
    ]
    cases = []
    for n in names:
        for suffix in (".yaml", ""):

            def run(d, n=n, suffix=suffix):
                path = d / (n + suffix)
                out = cli(["init", path])
                if out.exit == 0:
                    loaded, _ = call_api(lambda: api.load(path))
                    if loaded.exception is not None:
                        out.wrong = f"init wrote a starter run refuses: {loaded.message}"
                    if "\x1b" in out.message or ("\n" in n and n in out.message):
                        out.wrong = "a path echoed raw"
                return out

            cases.append(Case("init", f"init {n[:40]!r}{suffix}", run, n in ("report", "1", "_x")))
    for label in ("exists", "dangling-symlink", "dir", "very-long-path", "readonly-dir", "fifo"):

        def run(d, label=label):
            p = d / "s.yaml"
            if label == "exists":
                p.write_text("keep")
            elif label == "dangling-symlink":
                p.symlink_to(d / "nowhere")
            elif label == "dir":
                p.mkdir()
            elif label == "very-long-path":
                p = Path("/".join(["d" * 200] * 25) + "/s.yaml")
            elif label == "readonly-dir":
                os.chmod(d, 0o555)
            elif label == "fifo":
                os.mkfifo(p)
            try:
                out = cli(["init", p])
            finally:
                os.chmod(d, 0o755)
            if label == "exists" and p.read_text() != "keep":
                out.data_loss = ["s.yaml"]
            if label == "dangling-symlink" and (d / "nowhere").exists():
                out.wrong = "init followed a dangling symlink"
            return out

        cases.append(Case("init", f"init {label}", run))
    return cases


# ------------------------------------------------------------------------------------------
# Family 9: real processes (signals, closed or full streams, exit codes)


def process_cases() -> list[Case]:
    cases = []
    for label, args, expect in [
        ("version", ["--version"], 0),
        ("help", ["-h"], 0),
        ("no-args", [], None),
        ("kinds-dev-full", ["kinds"], 74),
        ("check-dev-full", ["check", "RES"], 74),
        ("init-dev-full", ["init", "D/new.yaml"], 74),
        ("run-dev-full", ["run", "S", "--out", "D/o"], 74),
        ("report-dev-full", ["report", "RES", "--out", "D/rep"], 74),
    ]:

        def run(d, args=args, expect=expect, label=label):
            res = h.T.results(d / "res")
            write_yaml(d / "s.yaml", tiny(name="small"))
            a = [
                str(x)
                .replace("RES", str(res))
                .replace("D/", f"{d}/")
                .replace("S", str(d / "s.yaml"))
                if x in ("RES", "S") or str(x).startswith("D/")
                else x
                for x in args
            ]
            stdout = open("/dev/full", "w") if "dev-full" in label else subprocess.PIPE  # noqa: SIM115
            try:
                env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
                p = subprocess.run(
                    [sys.executable, "-m", "anfekf_bench.entry", *a],
                    cwd=d,
                    env=env,
                    stdout=stdout,
                    stderr=subprocess.PIPE,
                    text=True,
                    timeout=120,
                )
            finally:
                if stdout is not subprocess.PIPE:
                    stdout.close()
            out = Outcome(exit=p.returncode)
            judge_output(out, (p.stdout or "") + p.stderr)
            if expect is not None and p.returncode != expect:
                out.wrong = f"exit {p.returncode}, expected {expect}"
            return out

        cases.append(Case("process", label, run, label == "kinds-dev-full"))
    # closed stdout, stdout to a pipe closed at once
    for label, cmd in [
        ("kinds-closed-stdout", "kinds >&-"),
        ("kinds-head", "kinds | head -c1"),
        ("help-closed-stderr", "--bogus 2>&-"),
        ("check-head", "check RES | head -c1"),
    ]:

        def run(d, cmd=cmd):
            res = h.T.results(d / "res")
            env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
            command = cmd.replace("RES", str(res))
            line = f"{sys.executable} -m anfekf_bench.entry {command}; echo rc=$? >&2"
            p = subprocess.run(
                ["bash", "-o", "pipefail", "-c", line],
                cwd=d,
                env=env,
                capture_output=True,
                text=True,
                timeout=120,
            )
            out = Outcome(exit=p.returncode)
            judge_output(out, p.stdout + p.stderr)
            return out

        cases.append(Case("process", label, run))
    # signals at random instants during a batch, then the same command again
    rng = random.Random(32)
    for i in range(16):
        sig = [signal.SIGINT, signal.SIGTERM, signal.SIGKILL][i % 3]
        delay = rng.uniform(0.3, 4.0)

        def run(d, sig=sig, delay=delay, i=i):
            h.T.results(d / "out", ("sib",) if i % 2 else ("small", "sib"))
            write_yaml(d / "s.yaml", tiny(name="small", runs=3))
            env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
            before = sha_tree(d / "out")
            force = ["--force"] if i % 2 == 0 else []
            p = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "anfekf_bench.entry",
                    "run",
                    d / "s.yaml",
                    "--out",
                    d / "out",
                    *force,
                ],
                cwd=d,
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                start_new_session=True,
            )
            time.sleep(delay)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, sig)
            so, se = p.communicate(timeout=120)
            out = Outcome(exit=p.returncode)
            judge_output(out, so + se)
            # the previous complete result of a forced rerun: intact or replaced whole, never mixed
            after = sha_tree(d / "out")
            out.data_loss = lost(before, after, ("small",) if force else ())
            again, text = proc(["run", d / "s.yaml", "--out", d / "out", "--force"], d)
            out.traceback = out.traceback or again.traceback
            if again.exit != 0 or run_count(d / "out/small") != 3:
                out.wrong = (
                    f"rerun after {sig.name}: exit {again.exit}, {run_count(d / 'out/small')} runs"
                )
            out.message += f" | {sig.name} after {delay:.1f}s; rerun: {text[-200:]}"
            return out

        cases.append(Case("process", f"{signal.Signals(sig).name} after {delay:.1f}s", run))
    return cases
