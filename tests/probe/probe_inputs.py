"""Probe cases on the input side: scenario files (every field of the schema, YAML itself),
noise schedules, training, filters lists, recorded-data fields, and command-line flags."""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path

import probe_harness as h
import yaml
from probe_harness import (
    ROOT,
    Case,
    api,
    call_api,
    cli,
    lost,
    run_case_cli,
    sha_tree,
    tiny,
    write_yaml,
)

# ------------------------------------------------------------------------------------------
# Family 1: scenario YAML mutations (every field of the schema)

BAD_VALUES: list[tuple[str, object]] = [
    ("negative", -1),
    ("zero", 0),
    ("huge", 1e308),
    ("hugeint", 2**70),
    ("nan", "nan"),
    ("inf", "inf"),
    ("-inf", "-inf"),
    ("empty", ""),
    ("unicode", "é€😀"),
    ("control", "a\x07\x1b[31m"),
    ("long", "x" * 5000),
    ("list", [1, 2]),
    ("map", {"a": 1}),
    ("null", None),
    ("bool", True),
    ("numtext", "1e3"),
    ("nested", [[[1]]]),
]

SCALAR_FIELDS = [
    "name",
    "description",
    "seed",
    "runs",
    "jobs",
    "record_every",
    "steps_table",
    "engine",
    "world.landmarks",
    "world.waypoints",
    "world.loops",
    "world.speed",
    "world.wheelbase",
    "world.max_steer_deg",
    "world.max_steer_rate_deg",
    "world.dt",
    "world.sensor_every",
    "world.max_range",
    "world.fov_deg",
    "world.waypoint_tolerance",
    "world.max_steps",
    "true_noise.sigma_v",
    "true_noise.sigma_gamma_deg",
    "true_noise.sigma_range",
    "true_noise.sigma_bearing_deg",
    "filter_noise.sigma_v",
    "filter_noise.sigma_range",
    "filter_noise.sigma_bearing_deg",
    "filter_noise.sigma_gamma_deg",
    "gate_probability",
    "filters",
    "starts",
    "backend.kind",
    "backend.scheduler",
    "backend.connect_timeout_s",
    "claims",
    "sweep",
    "compare",
    "training",
    "training.runs",
    "noise_schedule",
    "world",
    "true_noise",
    "filter_noise",
    "backend",
]

# Values a field accepts although they look odd (the schema allows them): no wrong result.
MAY_ACCEPT = {("description", v) for v in ("empty", "unicode", "long", "numtext", "control")} | {
    ("name", "unicode"),
    ("name", "numtext"),
    ("steps_table", "bool"),
    ("gate_probability", "null"),
    ("starts", "null"),
    ("backend.scheduler", "null"),
    ("sweep", "null"),
    ("noise_schedule", "null"),
    ("claims", "empty"),
    ("compare", "empty"),
    ("world.landmarks", "numtext"),
    ("world.waypoints", "numtext"),
    ("world.max_steps", "null"),
    ("world.speed", "numtext"),
    ("world.max_steer_rate_deg", "numtext"),
    ("world.max_range", "numtext"),
    ("world.max_range", "huge"),
    ("true_noise.sigma_range", "numtext"),
    ("filter_noise.sigma_range", "numtext"),
    ("backend.connect_timeout_s", "numtext"),
    ("world.max_steps", "numtext"),
    ("world.max_steps", "huge"),
    ("world.max_steps", "hugeint"),
    ("world.waypoint_tolerance", "numtext"),
    ("world.wheelbase", "numtext"),
    ("record_every", "numtext"),
    ("world.sensor_every", "numtext"),
    ("training.runs", "numtext"),
    ("seed", "numtext"),
    ("runs", "numtext"),
    ("jobs", "numtext"),
    ("world.loops", "bool"),
    ("runs", "bool"),
    ("jobs", "bool"),
    ("record_every", "bool"),
    ("world.sensor_every", "bool"),
    ("seed", "bool"),
    ("training.runs", "bool"),
    ("world.max_steps", "bool"),
    # text that is a valid name or description; 0 is a valid seed; YAML 0 reads as false; a
    # numeric text within range; a list of start factors
    ("name", "nan"),
    ("name", "inf"),
    ("description", "nan"),
    ("description", "inf"),
    ("description", "-inf"),
    ("seed", "zero"),
    ("steps_table", "zero"),
    ("true_noise.sigma_v", "numtext"),
    ("filter_noise.sigma_v", "numtext"),
    ("starts", "list"),
}


def set_path(doc: dict, dotted: str, value) -> dict:
    doc = copy.deepcopy(doc)
    *parents, last = dotted.split(".")
    node = doc
    for p in parents:
        node = node.setdefault(p, {}) if isinstance(node.get(p), dict) or p not in node else node[p]
    node[last] = value
    return doc


def scenario_cases() -> list[Case]:
    cases = []
    for fld in SCALAR_FIELDS:
        for label, value in BAD_VALUES:
            if fld == "name" and label == "long":
                value = "n" * 300
            doc = set_path(tiny(), fld, value)
            if label == "numtext" and fld in ("world.speed", "world.max_steer_rate_deg"):
                doc = set_path(doc, fld, "3")
            may = (fld, label) in MAY_ACCEPT
            listed = fld in ("runs", "seed") and label in ("negative", "bool")
            cases.append(
                Case(
                    "scenario",
                    f"{fld}={label}",
                    (
                        lambda d, doc=doc, may=may: run_case_cli(
                            d, doc, expect=None if may else "refuse"
                        )
                    ),
                    listed,
                )
            )
    # YAML-level mutations
    base = yaml.safe_dump(tiny(), sort_keys=False)
    raw = {
        "duplicate-key": base + "runs: 2\n",
        "duplicate-nested": base.replace("world:\n", "world:\n  loops: 1\n  loops: 2\n"),
        "unknown-key": base + "bogus: 1\n",
        "unknown-nested": base.replace("world:\n", "world:\n  bogus: 1\n"),
        "top-list": "- 1\n- 2\n",
        "top-scalar": "42\n",
        "top-null": "",
        "only-comment": "# x\n",
        "tabs": base.replace("  ", "\t"),
        "bom": "\ufeff" + base,
        "crlf": base.replace("\n", "\r\n"),
        "python-tag": base + "x: !!python/object/apply:os.system ['echo pwned']\n",
        "anchors-bomb": "a: &a [1,1,1,1,1,1,1,1,1]\nb: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]\n"
        "c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]\nd: &d [*c,*c,*c,*c,*c,*c,*c,*c,*c]\n"
        "e: &e [*d,*d,*d,*d,*d,*d,*d,*d,*d]\nf: [*e,*e,*e,*e,*e,*e,*e,*e,*e]\n",
        "deep-nesting": "a: " + "[" * 5000 + "]" * 5000 + "\n",
        "unclosed": base + "x: [1, 2\n",
        "bad-indent": base + "  y: 1\n z: 2\n",
        "lone-surrogate": "RAW:" + base.replace("small", "s\udcff"),
        "nul-byte": base.replace("small", "sm\x00all"),
        "latin1": None,
        "huge-file": base + "description: '" + "x" * 3_000_000 + "'\n",
        "merge-key": "base: &b {runs: 1}\n" + base.replace("runs: 1\n", "<<: *b\n"),
        "set-tag": base + "y: !!set {a, b}\n",
        "binary-tag": base + "y: !!binary aGVsbG8=\n",
        "timestamp": base.replace("seed: 7", "seed: 2001-12-14"),
        "octal-seed": base.replace("seed: 7", "seed: 0o17"),
        "hex-seed": base.replace("seed: 7", "seed: 0x10"),
        "underscore-int": base.replace("seed: 7", "seed: 1_000"),
        "sexagesimal": base.replace("seed: 7", "seed: 1:30"),
        "yes-bool": base + "steps_table: yes\n",
        "two-docs": base + "---\n" + base,
        "key-int": base + "1: 2\n",
        "key-null": base + "~: 2\n",
        "key-list": base + "? [a]\n: 1\n",
    }
    for label, text in raw.items():

        def run(d, text=text, label=label):
            if label == "latin1":
                (d / "s.yaml").write_bytes(base.replace("small", "sm\xe9ll").encode("latin-1"))
                return run_case_cli(d, d / "s.yaml")
            return run_case_cli(d, text if text.startswith("RAW:") else "RAW:" + text)

        cases.append(Case("scenario-yaml", label, run))
    return cases


# ------------------------------------------------------------------------------------------
# Family 2: noise schedules, training, filters lists, recorded-data fields


def schedule_cases() -> list[Case]:
    ch = lambda f, s=0, e=None, chans=("R",), shape="step": {  # noqa: E731
        "channels": list(chans),
        "factor": f,
        "start_s": s,
        "end_s": e,
        "shape": shape,
    }
    variants = {
        "factor-1e6": ({"changes": [ch(1e6)]}, "ok"),
        "factor-1e7": ({"changes": [ch(1e7)]}, "refuse"),
        "factor-1e-6": ({"changes": [ch(1e-6)]}, "ok"),
        "factor-1e-300": ({"changes": [ch(1e-300)]}, "refuse"),
        "factor-0": ({"changes": [ch(0)]}, "refuse"),
        "factor-neg": ({"changes": [ch(-4)]}, "refuse"),
        "factor-nan": ({"changes": [ch("nan")]}, "refuse"),
        "factor-inf": ({"changes": [ch("inf")]}, "refuse"),
        "factor-text": ({"changes": [ch("big")]}, "refuse"),
        "52x1e6": ({"changes": [ch(1e6)] * 52}, "refuse"),
        "two-1e4": ({"changes": [ch(1e4), ch(1e4)]}, "refuse"),
        "two-1e-4": ({"changes": [ch(1e-4), ch(1e-4)]}, "refuse"),
        "1e6-and-1e-6": ({"changes": [ch(1e6), ch(1e-6)]}, "ok"),
        "ramp-1e6": ({"changes": [ch(1e6, 0, 5, shape="ramp")]}, "ok"),
        "ramp-two": (
            {"changes": [ch(1e4, 0, 5, shape="ramp"), ch(1e4, 0, 5, shape="ramp")]},
            "refuse",
        ),
        "ramp-no-end": ({"changes": [ch(4, 0, None, shape="ramp")]}, None),
        "end-before-start": ({"changes": [ch(4, 10, 5)]}, "refuse"),
        "start-neg": ({"changes": [ch(4, -1)]}, "refuse"),
        "start-huge": ({"changes": [ch(4, 1e308)]}, None),
        "start-inf": ({"changes": [ch(4, "inf")]}, "refuse"),
        "channels-empty": ({"changes": [ch(4, chans=())]}, "refuse"),
        "channels-bogus": ({"changes": [ch(4, chans=("bogus",))]}, "refuse"),
        "channels-dup": ({"changes": [ch(4, chans=("R", "R"))]}, None),
        "channels-all": (
            {"changes": [ch(4, chans=("speed", "steering", "range", "bearing"))]},
            None,
        ),
        "shape-bogus": ({"changes": [ch(4, shape="cubic")]}, "refuse"),
        "changes-map": ({"changes": {"a": 1}}, "refuse"),
        "changes-1000": ({"changes": [ch(1.001)] * 1000}, None),
        "outliers-cont": (
            {"outliers": {"model": "contaminated", "probability": 0.05, "variance_factor": 400}},
            "ok",
        ),
        "outliers-p0": (
            {"outliers": {"model": "contaminated", "probability": 0, "variance_factor": 400}},
            "refuse",
        ),
        "outliers-p1-1e6": (
            {"outliers": {"model": "contaminated", "probability": 1, "variance_factor": 1e6}},
            "ok",
        ),
        "outliers-p1-1e6-times-change": (
            {
                "outliers": {"model": "contaminated", "probability": 1, "variance_factor": 1e6},
                "changes": [ch(10)],
            },
            "refuse",
        ),
        "outliers-vf1": (
            {"outliers": {"model": "contaminated", "probability": 0.5, "variance_factor": 1}},
            "refuse",
        ),
        "student-dof2": ({"outliers": {"model": "student_t", "dof": 2}}, "refuse"),
        "student-dof2.0000001": ({"outliers": {"model": "student_t", "dof": 2.0000001}}, "refuse"),
        "student-dof3": ({"outliers": {"model": "student_t", "dof": 3}}, "ok"),
        "student-dof1e6": ({"outliers": {"model": "student_t", "dof": 1e6}}, "ok"),
        "student-with-p": (
            {"outliers": {"model": "student_t", "dof": 3, "probability": 0.1}},
            None,
        ),
        "outliers-bad-model": ({"outliers": {"model": "cauchy"}}, "refuse"),
        "outliers-channel-speed": (
            {"outliers": {"model": "student_t", "dof": 3, "channels": ["speed"]}},
            "refuse",
        ),
        "blackout-all": ({"blackouts": [{"start_s": 0, "end_s": 1e6}]}, "ok"),
        "blackout-inverted": ({"blackouts": [{"start_s": 5, "end_s": 1}]}, "refuse"),
        "blackout-empty": ({"blackouts": [{"start_s": 5, "end_s": 5}]}, None),
        "blackout-overlap": (
            {"blackouts": [{"start_s": 0, "end_s": 5}, {"start_s": 2, "end_s": 8}]},
            None,
        ),
        "blackout-nan": ({"blackouts": [{"start_s": "nan", "end_s": 5}]}, "refuse"),
        "schedule-empty": ({}, None),
        "schedule-list": ([], "refuse"),
        "schedule-text": ("x", "refuse"),
        "schedule-unknown": ({"bogus": 1}, "refuse"),
    }
    cases = []
    for label, (schedule, expect) in variants.items():
        doc = tiny(noise_schedule=schedule)
        listed = label in ("52x1e6", "factor-1e-300")
        cases.append(
            Case(
                "schedule",
                label,
                lambda d, doc=doc, e=expect: run_case_cli(d, doc, expect=e),
                listed,
            )
        )
    # training settings with a fitted filter (ekf-ml: a noise fit on training runs)
    fitted = [{"name": "ekf", "kind": "ekf"}, {"name": "ekf-ml", "kind": "ekf-ml"}]
    for label, training, expect in [
        ("runs-1", {"runs": 1}, "ok"),
        ("runs-0", {"runs": 0}, "refuse"),
        ("runs-neg", {"runs": -3}, "refuse"),
        ("runs-10001", {"runs": 10001}, "refuse"),
        ("runs-text", {"runs": "many"}, "refuse"),
        ("runs-float", {"runs": 2.5}, "refuse"),
        ("unknown", {"bogus": 1}, "refuse"),
        ("list", [1], "refuse"),
        ("null", None, None),
        ("runs-2", {"runs": 2}, "ok"),
    ]:
        doc = tiny(filters=fitted, training=training)
        cases.append(
            Case("training", label, lambda d, doc=doc, e=expect: run_case_cli(d, doc, expect=e))
        )
    return cases


def filters_cases() -> list[Case]:
    ekf = {"name": "ekf", "kind": "ekf"}
    variants = {
        "empty-list": ([], "refuse"),
        "kind-bogus": ([{"name": "x", "kind": "bogus"}], "refuse"),
        "kind-missing": ([{"name": "x"}], "refuse"),
        "name-missing": ([{"kind": "ekf"}], None),
        "kind-int": ([{"name": "x", "kind": 3}], "refuse"),
        "kind-null": ([{"name": "x", "kind": None}], "refuse"),
        "dup-names": ([ekf, ekf], "refuse"),
        "name-slash": ([{"name": "a/b", "kind": "ekf"}], None),
        "name-dotdot": ([{"name": "..", "kind": "ekf"}], None),
        "name-esc": ([{"name": "\x1b[31mred", "kind": "ekf"}], None),
        "name-empty": ([{"name": "", "kind": "ekf"}], "refuse"),
        "name-long": ([{"name": "f" * 5000, "kind": "ekf"}], None),
        "name-unicode": ([{"name": "ékf😀", "kind": "ekf"}], None),
        "unknown-param": ([{"name": "x", "kind": "ekf", "bogus": 1}], "refuse"),
        "adapt-bogus": ([{"name": "a", "kind": "anfekf", "adapt": "Z"}], "refuse"),
        "adapt-int": ([{"name": "a", "kind": "anfekf", "adapt": 1}], "refuse"),
        "adapt-RQ": ([{"name": "a", "kind": "anfekf", "adapt": "RQ"}], "ok"),
        "akhlaghi-alpha-neg": ([{"name": "a", "kind": "akhlaghi", "alpha": -1}], "refuse"),
        "akhlaghi-alpha-2": ([{"name": "a", "kind": "akhlaghi", "alpha": 2}], "refuse"),
        "akhlaghi-alpha-nan": ([{"name": "a", "kind": "akhlaghi", "alpha": "nan"}], "refuse"),
        "filter-scalar": (["ekf"], "refuse"),
        "filter-list": ([["ekf"]], "refuse"),
        "filters-map": ({"ekf": "ekf"}, "refuse"),
        "many-100": ([{"name": f"e{i}", "kind": "ekf"} for i in range(100)], None),
        "kalmannet-hidden-0": ([{"name": "k", "kind": "kalmannet", "hidden_size": 0}], "refuse"),
        "kalmannet-hidden-neg": ([{"name": "k", "kind": "kalmannet", "hidden_size": -5}], "refuse"),
        "kalmannet-hidden-huge": (
            [{"name": "k", "kind": "kalmannet", "hidden_size": 10**9}],
            "refuse",
        ),
        "kalmannet-epochs-0": ([{"name": "k", "kind": "kalmannet", "epochs": 0}], "refuse"),
        "vb-rho-0": ([{"name": "v", "kind": "vb-r", "rho": 0}], None),
        "vb-rho-2": ([{"name": "v", "kind": "vb-r", "rho": 2}], None),
        "sage-b-1": ([{"name": "s", "kind": "sage-husa", "b": 1}], None),
        "sage-b-neg": ([{"name": "s", "kind": "sage-husa", "b": -1}], "refuse"),
        "iae-window-0": ([{"name": "i", "kind": "iae", "window": 0}], "refuse"),
        "iae-window-huge": ([{"name": "i", "kind": "iae", "window": 10**9}], None),
        "imm-empty": ([{"name": "i", "kind": "imm", "factors": []}], "refuse"),
        "cm-scale": ([{"name": "c", "kind": "cm-scale", "adapt": "R"}], "ok"),
        "oracle-only": ([{"name": "o", "kind": "ekf-oracle"}], "ok"),
        "compare-unknown": (None, "refuse"),
        "claim-unknown-filter": (None, "refuse"),
        "claim-both-bounds": (None, None),
        "claim-no-bound": (None, None),
        "claim-bad-metric": (None, "refuse"),
        "claim-inf-bound": (None, "refuse"),
        "starts-many": (None, None),
        "starts-zero": (None, "refuse"),
    }
    cases = []
    for label, (filters, expect) in variants.items():
        doc = tiny()
        if filters is not None:
            doc["filters"] = filters
        claim = {"filter": "ekf-oracle", "vs": "ekf", "metric": "rmse_pos"}
        if label == "compare-unknown":
            doc["compare"] = [["ekf", "nope"]]
        elif label == "claim-unknown-filter":
            doc["claims"] = [dict(claim, filter="nope", at_most=1)]
        elif label == "claim-both-bounds":
            doc["claims"] = [dict(claim, at_most=1, at_least=2)]
        elif label == "claim-no-bound":
            doc["claims"] = [claim]
        elif label == "claim-bad-metric":
            doc["claims"] = [dict(claim, metric="bogus", at_most=1)]
        elif label == "claim-inf-bound":
            doc["claims"] = [dict(claim, at_most="inf")]
        elif label == "starts-many":
            doc["starts"] = [0.5, 1, 2]
        elif label == "starts-zero":
            doc["starts"] = [0]
        cases.append(
            Case("filters", label, lambda d, doc=doc, e=expect: run_case_cli(d, doc, expect=e))
        )
    return cases


def recorded_cases() -> list[Case]:
    """Recorded-data scenario fields, validated by api.load (loading the log, no batch)."""
    base = yaml.safe_load((ROOT / "configs/real/mrclam-d9.yaml").read_text())
    base["filters"] = base["filters"][:2]
    variants = {
        "unchanged": ("name", "mrclam-d9"),
        "data-kind-bogus": ("data.kind", "bogus"),
        "data-path-missing": ("data.path", "/nonexistent/x"),
        "data-path-dir": ("data.path", "/tmp"),
        "data-path-etc": ("data.path", "/etc/passwd"),
        "data-path-empty": ("data.path", ""),
        "data-path-nul": ("data.path", "a\x00b"),
        "data-path-int": ("data.path", 3),
        "data-null": ("data", None),
        "data-list": ("data", [1]),
        "data-unknown": ("data.bogus", 1),
        "split-0": ("split_fraction", 0),
        "split-1": ("split_fraction", 1),
        "split-neg": ("split_fraction", -0.5),
        "split-nan": ("split_fraction", "nan"),
        "split-text": ("split_fraction", "half"),
        "segment-0": ("segment_s", 0),
        "segment-neg": ("segment_s", -60),
        "segment-huge": ("segment_s", 1e308),
        "segment-inf": ("segment_s", "inf"),
        "naive-neg": ("naive.sigma_v", -1),
        "naive-zero": ("naive.sigma_range", 0),
        "naive-nan": ("naive.sigma_bearing_rad", "nan"),
        "naive-unknown": ("naive.bogus", 1),
        "naive-list": ("naive", [1]),
        "starts-empty": ("starts", []),
        "starts-neg": ("starts", [-1]),
        "starts-text": ("starts", ["x"]),
        "gate-1": ("gate_probability", 1),
        "gate-0": ("gate_probability", 0),
        "runs-field": ("runs", 5),
        "world-field": ("world.loops", 2),
        "true-noise-field": ("true_noise.sigma_v", 1),
        "jobs-0": ("jobs", 0),
        "seed-neg": ("seed", -1),
        "name-empty": ("name", ""),
        "filters-empty": ("filters", []),
        "sweep-field": ("sweep", {"axes": [{"scale": "R", "values": [1, 2]}]}),
        "noise-schedule": ("noise_schedule", {"changes": []}),
        "training": ("training.runs", 3),
        "data-path-relative": ("data.path", "../../x.csv"),
    }
    cases = []
    for label, (fld, value) in variants.items():
        doc = set_path(base, fld, value)

        def run(d, doc=doc, label=label):
            out, _ = call_api(lambda: api.load(doc, base=ROOT / "configs/real"))
            if label == "unchanged" and out.exception is not None:
                out.wrong = "the shipped recorded scenario was refused"
            return out

        cases.append(Case("recorded", label, run))
    return cases


# ------------------------------------------------------------------------------------------
# Family 3: command-line flags


def flag_cases() -> list[Case]:
    cases = []
    doc = tiny(name="small")
    for flag, values in {
        "--runs": ["0", "-1", "abc", "1e3", str(2**64), "", "2.5", "100001", " 2", "2"],
        "--jobs": ["0", "-2", "x", "1025", "99999999999", "1"],
        "--seed": ["-1", str(2**63), str(2**63 - 1), "0x10", "nan", "3"],
        "--engine": ["bogus", "", "FAST", "filterpy"],
        "--backend": ["bogus", "dask", "local"],
        "--scheduler": ["nope", "tcp://", "tcp://127.0.0.1:1", "\x1b[2J"],
    }.items():
        for v in values:
            expect = "ok" if v in ("2", "1", "3", "filterpy", "local", str(2**63 - 1)) else None
            if flag == "--scheduler":
                expect = None
            runs = 2 if flag == "--runs" and v.strip() == "2" else None
            cases.append(
                Case(
                    "flags",
                    f"run {flag} {v!r}",
                    (
                        lambda d, flag=flag, v=v, e=expect, runs=runs: run_case_cli(
                            d, doc, [flag, v], expect=e, runs=runs, name="small"
                        )
                    ),
                    flag in ("--runs", "--seed") and v in ("-1",),
                )
            )
    combos = [
        (["--force", "--skip-existing"], "refuse"),
        (["--force"], "ok"),
        (["--skip-existing"], "ok"),
        (["--backend", "dask"], None),
        (["--scheduler", "tcp://127.0.0.1:9"], None),
        (["--runs"], "refuse"),
        (["--bogus"], "refuse"),
        (["--debug", "--runs", "0"], "refuse"),
        (["--engine", "fast", "--runs", "2"], None),  # the same runs and seed: held
    ]
    for extra, expect in combos:

        def run(d, extra=extra, expect=expect):
            h.T.results(d / "out", ("small", "sib"))
            force = "--force" in extra
            return run_case_cli(
                d,
                h.T.small_doc,
                [e for e in extra if e != "--force"],
                expect=expect,
                force=force,
                name="small",
                prepare=False,
                runs=2 if "--runs" in extra and expect == "ok" else None,
            )

        cases.append(Case("flags", "run " + " ".join(extra), run))
    # the scenario argument
    for label, make in {
        "missing": lambda d: d / "nope.yaml",
        "empty-dir": lambda d: (d / "e").mkdir() or d / "e",
        "dir-of-two-same-name": lambda d: (
            (d / "two").mkdir()
            or write_yaml(d / "two/a.yaml", tiny())
            and write_yaml(d / "two/b.yaml", tiny())
            and d / "two"
        ),
        "dir-of-bad": lambda d: (
            (d / "bad").mkdir() or (d / "bad/x.yaml").write_text("runs: [") or d / "bad"
        ),
        "fifo": lambda d: os.mkfifo(d / "f.yaml") or d / "f.yaml",
        "dev-null": lambda d: Path("/dev/null"),
        "a-result-folder": lambda d: h.T.results(d / "r", ("small",)) / "small",
        "binary": lambda d: (d / "b.yaml").write_bytes(os.urandom(2000)) or d / "b.yaml",
        "unreadable": lambda d: (
            (d / "u.yaml").write_text("x: 1") or os.chmod(d / "u.yaml", 0) or d / "u.yaml"
        ),
        "json-file": lambda d: (d / "s.json").write_text(json.dumps(tiny())) or d / "s.json",
        "nul-in-path": lambda d: Path("a\x00b.yaml"),
        "very-long-path": lambda d: Path("x" * 5000 + ".yaml"),
        "esc-in-path": lambda d: d / "\x1b[31m.yaml",
    }.items():

        def run(d, make=make):
            out = run_case_cli(d, make(d))
            return out

        cases.append(Case("flags", f"run SCENARIO={label}", run))
    # report
    for label, args, expect in [
        ("format-bogus", ["--format", "gif"], "refuse"),
        ("format-empty", ["--format", ""], "refuse"),
        ("dpi-0", ["--dpi", "0"], "refuse"),
        ("dpi-huge", ["--dpi", "99999"], "refuse"),
        ("dpi-text", ["--dpi", "x"], "refuse"),
        ("missing-results", ["MISSING"], "refuse"),
        ("results-file", ["FILE"], "refuse"),
        ("results-empty-dir", ["EMPTY"], "refuse"),
        ("out-is-file", ["--out", "FILE"], "refuse"),
        ("out-inside-result", ["--out", "IN"], None),
        ("svg", ["--format", "svg"], "ok"),
        ("two-same", ["RES", "RES"], None),
        ("out-is-results", ["--out", "RES"], None),
    ]:

        def run(d, args=args, expect=expect):
            res = h.T.results(d / "res")
            (d / "file").write_text("x")
            (d / "empty").mkdir()
            sub = {
                "MISSING": d / "missing",
                "FILE": d / "file",
                "EMPTY": d / "empty",
                "IN": res / "small" / "rep",
                "RES": res,
            }
            a = [sub.get(x, x) for x in args]
            if (
                not any(x in args for x in ("MISSING", "FILE", "EMPTY", "RES"))
                or args[0] == "--out"
            ):
                a = [res, *a]
            if "--out" not in args:
                a += ["--out", d / "report"]
            before = sha_tree(res)
            out = cli(["report", *a])
            out.data_loss = lost(before, sha_tree(res))
            if expect == "refuse" and out.exit == 0:
                out.wrong = "accepted"
            if expect == "ok" and out.exit != 0:
                out.wrong = "refused"
            return out

        cases.append(Case("flags", f"report {label}", run))
    # check, kinds, init, root
    for label, args in [
        ("check-missing", ["check", "/nonexistent"]),
        ("check-file", ["check", "/etc/hostname"]),
        ("check-update-no-baseline", ["check", "RES", "--update"]),
        ("check-baseline-dir", ["check", "RES", "--baseline", "/tmp"]),
        ("check-baseline-missing", ["check", "RES", "--baseline", "/nonexistent.json"]),
        ("check-update-into-dir", ["check", "RES", "--baseline", "DIR", "--update"]),
        ("check-update-readonly", ["check", "RES", "--baseline", "/proc/x.json", "--update"]),
        ("check-strict", ["check", "RES", "--strict"]),
        ("kinds-bogus", ["kinds", "bogus"]),
        ("kinds-esc", ["kinds", "\x1b[31m"]),
        ("kinds", ["kinds"]),
        ("kinds-ekf-twice", ["kinds", "ekf", "ekf"]),
        ("root-bogus", ["bogus"]),
        ("version", ["--version"]),
        ("help", ["--help"]),
        ("run-help", ["run", "--help"]),
        ("init-no-folder", ["init", "/nonexistent/x.yaml"]),
        ("init-dir", ["init", "DIR"]),
        (
            "bench-bad-configs",
            ["bench", "--quick", "--configs", "/nonexistent", "--out", "DIR/b.json"],
        ),
    ]:

        def run(d, args=args):
            res = h.T.results(d / "res")
            (d / "dir").mkdir()
            a = [{"RES": res, "DIR": d / "dir"}.get(x, x) for x in args]
            before = sha_tree(res)
            out = cli(a)
            out.data_loss = lost(before, sha_tree(res))
            return out

        cases.append(Case("flags", label, run))
    return cases
