"""Issue 32 (Hardening 4) and issue 38: `anfekf init` from any file name, noise schedules whose
factors multiply out of range, fit caches edited by hand, and training runs in the memory and
time estimate. Each case failed on main before its fix (docs/HARDENING.md, "Hardening 4")."""

from __future__ import annotations

import re
import threading
from pathlib import Path

import pytest
import typer
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from anfekf_bench import cli
from anfekf_bench.cli import app
from anfekf_bench.experiment import check_plan, make_plan
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.storage import scenario_name_problem

runner = CliRunner()

# --------------------------------------------------------------------------------------------
# `anfekf init` from any file name


def _init(path: Path):
    return runner.invoke(app, ["init", str(path)])


def _one_error_line(result) -> str:
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2, result.output
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert "Traceback" not in result.output and "\x1b" not in result.output
    return lines[0]


# The 13 classes refused on main (the name `init` wrote was one `anfekf run` refused), and more.
FILE_NAMES = [
    "report.yaml", "REPORT.yaml", "baselines.yaml", "ci-gate.yaml", "readme.md.yaml",
    "bench.json.yaml", "steps.parquet.yaml", "manifest.json.yaml", ".runs.yaml", ".lock.yaml",
    "x.tmp.yaml", "a.npz.yml", "s.yaml.yaml",  # the results layout's names and suffixes
    "_x.yaml", "__init__.yaml", ".x.yaml", ".hidden", "..yaml", "-dash.yaml", "_.yaml",
    "é.yaml", "café.yaml", "日本語.yaml", "🤖.yaml", "Ωmega.yml", "naïve-run.yaml",
    "a" * 65 + ".yaml", "b" * 200 + ".yaml", "c" * 246 + ".yaml", "_" * 80 + "x" * 70 + ".yaml",
    "1.yaml", "007.yaml", "1e5.yaml", "0x10.yaml", "1_000.yaml", "-1.yaml", ".inf.yaml",
    "true.yaml", "null.yaml", "yes.yaml", "off.yaml", "~.yaml", "nan.yaml",
    "my scenario.yaml", "a:b.yaml", "[x].yaml", "{y}.yaml", "#c.yaml", "'q'.yaml", '"d".yaml',
    "&anchor.yaml", "*alias.yaml", "!tag.yaml", "%pct.yaml", "@at.yaml", "`tick`.yaml",
    "tab\there.yaml", "new\nline.yaml", "esc\x1b[2J.yaml", "scenario", "noext", "x.txt",
    "wrong_r.yaml", "small.yaml", "v1.2.yaml",
]  # fmt: skip


def _accepted_by_run(path: Path) -> str:
    """The scenario's name, after what `anfekf run` validates before any work (the file and
    the name's rules)."""
    scenario, _ = load_scenario(path)
    assert isinstance(scenario.name, str) and scenario_name_problem(scenario.name) is None
    return scenario.name


@pytest.mark.parametrize("file_name", FILE_NAMES, ids=[ascii(n)[1:-1][:40] for n in FILE_NAMES])
def test_init_writes_a_starter_that_run_accepts_whatever_the_file_name(tmp_path, file_name):
    path = tmp_path / file_name
    result = _init(path)
    assert result.exit_code == 0, result.output
    assert "\x1b" not in result.output and len(result.output.strip().splitlines()) == 1
    name = _accepted_by_run(path)
    assert name in result.output  # the line names the scenario init derived


def test_init_keeps_a_plain_file_name_as_the_scenario_name(tmp_path):
    for stem in ("wrong_r", "v1.2", "Run-3"):
        _init(tmp_path / f"{stem}.yaml")
        assert _accepted_by_run(tmp_path / f"{stem}.yaml") == stem


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(stem=st.text(st.characters(blacklist_characters="/\x00"), min_size=1, max_size=120))
def test_any_file_name_gives_a_valid_starter_or_one_line(tmp_path, stem):
    folder = Path(tempfile_dir(tmp_path))
    path = folder / f"{stem}.yaml"
    result = _init(path)
    if result.exit_code == 0:
        _accepted_by_run(path)
        assert "\x1b" not in result.output and len(result.output.strip().splitlines()) == 1
    else:  # a name the file system refuses (too long in bytes): one line
        _one_error_line(result)


def tempfile_dir(tmp_path: Path) -> str:
    import tempfile

    return tempfile.mkdtemp(dir=tmp_path)


def test_init_long_names_and_paths_are_one_line(tmp_path):
    result = _init(tmp_path / ("d" * 256 + ".yaml"))  # over the file system's NAME_MAX
    assert "path" in _one_error_line(result) or "long" in result.output
    deep = tmp_path / "/".join(["e" * 200] * 25) / "x.yaml"  # a 5,000-character path
    _one_error_line(_init(deep))
    assert not list(tmp_path.iterdir())


def test_init_prints_paths_escaped(tmp_path):
    path = tmp_path / "esc\x1b[2Jx\ny.yaml"
    result = _init(path)
    assert result.exit_code == 0, result.output
    assert "\x1b" not in result.output and "\\x1b" in result.output
    assert len(result.output.strip().splitlines()) == 1
    again = _init(path)
    assert "\\x1b" in _one_error_line(again)


def test_init_refuses_anything_at_the_path(tmp_path):
    (tmp_path / "folder.yaml").mkdir()
    (tmp_path / "dangling.yaml").symlink_to(tmp_path / "nowhere")
    for name in ("folder.yaml", "dangling.yaml"):
        assert "already exists" in _one_error_line(_init(tmp_path / name))
    assert not (tmp_path / "nowhere").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []


def test_concurrent_inits_of_one_path_exactly_one_succeeds(tmp_path):
    """Eight writers race for each of 12 paths: exactly one creates it, the others are told it
    exists (main checked, then renamed over: several exited 0 and the last one won)."""
    writers = 8
    for i in range(12):
        path = tmp_path / f"race-{i}.yaml"
        start = threading.Barrier(writers)
        codes: list[int] = []

        def one(path=path, start=start, codes=codes) -> None:
            start.wait()
            try:
                cli.init(path)
                codes.append(0)
            except typer.Exit as exc:
                codes.append(exc.exit_code)

        threads = [threading.Thread(target=one) for _ in range(writers)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sorted(codes) == [0] + [2] * (writers - 1), (path.name, codes)
        assert _accepted_by_run(path) == f"race-{i}"
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []


# --------------------------------------------------------------------------------------------
# Issue 38: every commented-out option of the starter works when uncommented

OPTION_LINE = re.compile(r"^# ?([a-z_]+):\s")


def test_each_commented_out_option_of_the_starter_validates_when_uncommented(tmp_path):
    assert _init(tmp_path / "starter.yaml").exit_code == 0
    lines = (tmp_path / "starter.yaml").read_text().splitlines(keepends=True)
    options = [i for i, line in enumerate(lines) if OPTION_LINE.match(line)]
    assert {OPTION_LINE.match(lines[i])[1] for i in options} >= {"engine", "world"}
    for i in options:
        edited = [*lines[:i], re.sub(r"^# ?", "", lines[i]), *lines[i + 1 :]]
        path = tmp_path / f"option-{i}.yaml"
        path.write_text("".join(edited))
        scenario, world = load_scenario(path)  # main: "map file not found: builtin"
        check_plan(
            make_plan(scenario, world, None, None, None)
        )  # the route and the memory, as `run` checks


# --------------------------------------------------------------------------------------------
# Noise schedules: the factors in force at any instant multiply within [1e-6, 1e6]

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _scheduled(tmp_path: Path, schedule: dict) -> Path:
    from .conftest import small_scenario, write_scenario

    return write_scenario(tmp_path / "sched.yaml", small_scenario(noise_schedule=schedule))


def _step(factor: float, start: float = 0.0, end: float | None = None, channels=("range",)):
    return {"channels": list(channels), "factor": factor, "start_s": start, "end_s": end}


def _ramp(factor: float, start: float, end: float, channels=("range",)):
    return {**_step(factor, start, end, channels), "shape": "ramp"}


SCHEDULES_OUT_OF_RANGE = {
    # 52 valid factors of 1e6 at once: 1e312, past the float range (main: every run diverged)
    "steps-overflow": {"changes": [_step(1e6) for _ in range(52)]},
    "steps-two-of-1e6": {"changes": [_step(1e6, 0, 10), _step(1e6, 5, 20)]},
    "factor-1e-300": {"changes": [_step(1e-300)]},  # no lower bound on main
    "factor-below-1e-6": {"changes": [_step(1e-7, 3, 9)]},
    "ramp-to-1e-300": {"changes": [_ramp(1e-300, 3, 9)]},
    "steps-product-below": {"changes": [_step(1e-4, 0, 10), _step(1e-3, 2, 4, ["R"])]},
    "ramps-product-at-end": {"changes": [_ramp(1e4, 0, 10), _ramp(1e4, 5, 15, ["R"])]},
    # each pair cancels at both ends, but halfway (5e5)^2 x 0.5^2 = 6e10: only inside a segment
    "ramps-product-inside": {
        "changes": [_ramp(1e6, 0, 10), _ramp(1e6, 0, 10), _ramp(1e-6, 0, 10), _ramp(1e-6, 0, 10)]
    },
    "student-t-dof-near-2": {"outliers": {"model": "student_t", "dof": 2.0000001}},
    "outliers-times-change": {
        "changes": [_step(1e6, 0, 5, ["bearing"])],
        "outliers": {"model": "contaminated", "probability": 1.0, "variance_factor": 1e6},
    },
    "control-channel": {"changes": [_step(1e3, 0, None, ["Qu"]), _step(1e4, 1, 2, ["speed"])]},
}


@pytest.mark.parametrize("case", list(SCHEDULES_OUT_OF_RANGE))
def test_a_schedule_whose_factors_multiply_out_of_range_is_refused(tmp_path, case):
    from anfekf_bench.config import ScenarioError

    path = _scheduled(tmp_path, SCHEDULES_OUT_OF_RANGE[case])
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    message = str(err.value)
    assert message.startswith(f"{path}: noise_schedule"), message
    assert "[1e-06, 1e+06]" in message and "\n" not in message


def test_a_schedule_out_of_range_is_one_line_before_any_run(tmp_path):
    path = _scheduled(tmp_path, SCHEDULES_OUT_OF_RANGE["steps-overflow"])
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    line = _one_error_line(result)
    assert "noise_schedule" in line and "[1e-06, 1e+06]" in line
    assert not (tmp_path / "out").exists()


SCHEDULES_IN_RANGE = {
    "at-the-bounds": {"changes": [_step(1e3, 0, 10), _step(1e3, 10, 20), _step(1e-6, 20, 30)]},
    "bounds-met-exactly": {"changes": [_step(1e3), _step(1e3, 0, None, ["R"])]},
    "ramp-back": {"changes": [_ramp(1e6, 0, 10), _ramp(1e-6, 10, 20)]},
    "disjoint-steps": {"changes": [_step(1e6, 0, 5), _step(1e6, 5, 10), _step(1e6, 10, 15)]},
    "other-channels": {"changes": [_step(1e6, 0, None, ["range"]), _step(1e6, 0, None, ["Qu"])]},
    "blackouts": {"blackouts": [{"start_s": 0, "end_s": 1e7}, {"start_s": 5, "end_s": 6}]},
}


@pytest.mark.parametrize("case", list(SCHEDULES_IN_RANGE))
def test_a_schedule_within_range_is_accepted(tmp_path, case):
    load_scenario(_scheduled(tmp_path, SCHEDULES_IN_RANGE[case]))


def test_every_shipped_schedule_is_within_range():
    shipped = [p for p in CONFIGS.rglob("*.yaml") if "noise_schedule" in p.read_text()]
    assert len(shipped) >= 6
    for path in shipped:
        load_scenario(path)


# --------------------------------------------------------------------------------------------
# Fit caches in the run store: checked like run files, a bad one refitted with one warning


def _fit_scenario():
    from anfekf_bench.config import parse_scenario, resolve_world

    from .conftest import small_scenario

    doc = small_scenario(
        name="fitcache", runs=2, record_every=4, training={"runs": 3},
        filter_noise={"sigma_range": 0.5, "sigma_bearing_deg": 0.5},
        filters=[{"name": "ekf", "kind": "ekf"},
                 {"name": "ml", "kind": "ekf-ml", "starts": [1.0], "max_evaluations": 30}],
    )  # fmt: skip
    scenario = parse_scenario(doc)
    return scenario, resolve_world(scenario.world, ".")


@pytest.fixture(scope="module")
def fitted_cache(tmp_path_factory):
    """A real ekf-ml fit and its cache file (fitted once for the module)."""
    from anfekf_bench.fitting.simulated import fit_filters

    scenario, world = _fit_scenario()
    plan = make_plan(scenario, world, None, None, 1)
    store = tmp_path_factory.mktemp("store")
    fits = fit_filters(plan, store)
    (path,) = store.glob("fit-*.json")
    return plan, path.name, path.read_bytes(), fits.records["ml"]["fitted"]


def _rehashed(doc: dict) -> dict:
    """`doc` with its checksum recomputed: an edit only the content checks can see."""
    from anfekf_bench.outputs import fit_digest

    return {**doc, "sha256": fit_digest(doc["fingerprint"], doc["fitted"])}


def _with_sigma(doc: dict, value, drop: bool = False) -> dict:
    import copy

    doc = copy.deepcopy(doc)
    if drop:
        del doc["fitted"]["sigmas_rad"]["sigma_range"]
    else:
        doc["fitted"]["sigmas_rad"]["sigma_range"] = value
    return doc


def _json_bytes(doc) -> bytes:
    import json

    return json.dumps(doc).encode()


NOISE_FIT_TAMPERED = {
    "checksum-mismatch": lambda d: _json_bytes(_with_sigma(d, 0.3)),  # edited, not re-hashed
    "negative-sigma": lambda d: _json_bytes(_rehashed(_with_sigma(d, -0.3))),  # used silently
    "zero-sigma": lambda d: _json_bytes(_rehashed(_with_sigma(d, 0))),
    "string-sigma": lambda d: _json_bytes(_rehashed(_with_sigma(d, "0.3"))),
    "boolean-sigma": lambda d: _json_bytes(_rehashed(_with_sigma(d, True))),
    "missing-sigma": lambda d: _json_bytes(_rehashed(_with_sigma(d, None, drop=True))),
    "overflowing-sigma": lambda d: _json_bytes(_rehashed(_with_sigma(d, 1e300))),
    "wrong-format": lambda d: _json_bytes({**d, "format": "anfekf-bench fit v0"}),
    "another-fingerprint": lambda d: _json_bytes(_rehashed({**d, "fingerprint": "0" * 16})),
    "fitted-a-list": lambda d: _json_bytes(_rehashed({**d, "fitted": [1, 2]})),
    "non-utf8-bytes": lambda d: b'{"format": "\xff\xfe"}',
    "truncated": lambda d: _json_bytes(d)[:40],
    "nan": lambda d: _json_bytes(d).replace(b'"sigma_v": ', b'"sigma_v": NaN, "x": '),
    "empty": lambda d: b"",
}


@pytest.mark.parametrize("case", list(NOISE_FIT_TAMPERED))
def test_a_tampered_noise_fit_cache_is_refitted_with_a_warning(tmp_path, fitted_cache, case,
                                                                monkeypatch):  # fmt: skip
    import json

    from anfekf_bench.filters.fitted import EKFMLSpec
    from anfekf_bench.fitting.simulated import fit_filters
    from anfekf_bench.outputs import CachedFitRefused

    plan, name, good_bytes, good_fit = fitted_cache
    (tmp_path / name).write_bytes(NOISE_FIT_TAMPERED[case](json.loads(good_bytes)))
    calls = []

    def refit(self, training):
        calls.append(self.name)
        return good_fit

    monkeypatch.setattr(EKFMLSpec, "fit", refit)
    with pytest.warns(CachedFitRefused) as caught:
        fits = fit_filters(plan, tmp_path)
    assert calls == ["ml"] and fits.records["ml"]["cached"] is False
    (warning,) = [w for w in caught if issubclass(w.category, CachedFitRefused)]
    assert name in str(warning.message) and "fitted again" in str(warning.message)
    assert "\n" not in str(warning.message)
    spec = next(f for f in fits.scenario.filters if f.name == "ml")
    assert spec.fitted_sigmas() == tuple(good_fit["sigmas_rad"].values())  # never the bad one
    assert json.loads((tmp_path / name).read_text())["fitted"] == good_fit  # replaced


def test_an_intact_fit_cache_is_used_without_a_word(tmp_path, fitted_cache, monkeypatch):
    import warnings

    from anfekf_bench.filters.fitted import EKFMLSpec
    from anfekf_bench.fitting.simulated import fit_filters

    plan, name, good_bytes, good_fit = fitted_cache
    (tmp_path / name).write_bytes(good_bytes)
    monkeypatch.setattr(EKFMLSpec, "fit", lambda *a: pytest.fail("refitted an intact cache"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fits = fit_filters(plan, tmp_path)
    assert fits.records["ml"]["cached"] is True and fits.records["ml"]["fitted"] == good_fit


def test_a_tampered_fit_cache_on_resume_is_one_warning_line(tmp_path):
    """Through `anfekf run`: a batch stopped after its first run, its fit cache given a
    negative sigma (checksum recomputed), then the same command: one warning line, the fit
    computed again, the result's fit the good one (main used the negative sigma silently)."""
    import json

    from anfekf_bench.experiment import execute
    from anfekf_bench.storage import RUNS_DIR, read_manifest

    from .conftest import small_scenario, write_scenario

    doc = small_scenario(
        name="fitcache", runs=2, record_every=4, training={"runs": 3},
        filter_noise={"sigma_range": 0.5, "sigma_bearing_deg": 0.5},
        filters=[{"name": "ekf", "kind": "ekf"},
                 {"name": "ml", "kind": "ekf-ml", "starts": [1.0], "max_evaluations": 30}],
    )  # fmt: skip
    path = write_scenario(tmp_path / "fitcache.yaml", doc)
    plan = make_plan(*load_scenario(path), None, None, None)

    class Stop(Exception):
        pass

    def stop(_):
        raise Stop

    out = tmp_path / "out"
    with pytest.raises(Stop):
        execute(plan, out, on_result=stop)
    (cache,) = (out / "fitcache" / RUNS_DIR).glob("fit-*.json")
    good = json.loads(cache.read_text())
    cache.write_text(json.dumps(_rehashed(_with_sigma(good, -0.3))))
    result = runner.invoke(app, ["run", str(path), "--out", str(out)])
    assert result.exit_code == 0, result.output
    lines = [line for line in result.output.splitlines() if cache.name in line]
    assert len(lines) == 1 and lines[0].startswith("warning: ") and "fitted again" in lines[0]
    assert "sigma_range" in lines[0]
    fitted = read_manifest(out / "fitcache")["training"]["ml"]
    assert fitted["cached"] is False
    assert fitted["fitted"]["sigmas_rad"] == good["fitted"]["sigmas_rad"]


# KalmanNet's cached weights: checked without PyTorch (the cache file written by hand)


def _kalmannet_fit(hidden: int = 4) -> dict:
    from anfekf_bench.filters.kalmannet import KalmanNetSpec, KalmanNetWeights, TrainingResult

    weights = KalmanNetWeights.random(hidden_size=hidden, seed=3)
    result = TrainingResult(weights, 1.5, [0.5, 0.4], 1.2, [0.6, 0.5])
    return KalmanNetSpec.fitted_doc(result)


def _weights_bytes(hidden=4, **header_edits) -> bytes:
    import json

    from anfekf_bench.filters.kalmannet import KalmanNetWeights

    data = KalmanNetWeights.random(hidden_size=hidden, seed=3).to_bytes()
    head, _, body = data.partition(b"\n")
    header = {**json.loads(head), **header_edits}
    return json.dumps(header, sort_keys=True).encode() + b"\n" + body


def _with_weights(fitted: dict, data: bytes, rehash: bool = True) -> dict:
    import base64
    import hashlib

    out = {**fitted, "weights_base64": base64.b64encode(data).decode("ascii")}
    if rehash:
        out["weights_sha256"] = hashlib.sha256(data).hexdigest()
    return out


def _negative_shapes() -> bytes:
    import json

    head, _, body = _weights_bytes().partition(b"\n")
    header = json.loads(head)
    header["arrays"][0][1] = [-1]
    return json.dumps(header).encode() + b"\n" + body


def _nan_weight() -> bytes:
    import numpy as np

    data = bytearray(_weights_bytes())
    data[-8:] = np.array([np.nan]).tobytes()
    return bytes(data)


KALMANNET_FIT_TAMPERED = {
    "weights-hash-mismatch": lambda f: _with_weights(f, _weights_bytes()[:-8] + bytes(8), False),
    "negative-shape": lambda f: _with_weights(f, _negative_shapes()),
    "wrong-format": lambda f: _with_weights(f, _weights_bytes(format="other")),
    "zero-scale": lambda f: _with_weights(f, _weights_bytes(obs_scale=[0.0, 0.02])),
    "zero-range-scale": lambda f: _with_weights(f, _weights_bytes(range_scale=0)),
    "non-utf8-header": lambda f: _with_weights(f, b"\xff\xfe{}\n" + bytes(16)),
    "header-not-json": lambda f: _with_weights(f, b"not json\n"),
    "other-hidden-size": lambda f: _with_weights(f, _weights_bytes(hidden=6)),
    "other-shapes": lambda f: _with_weights(f, _weights_bytes(state_scale=[1.0, 1.0, 1.0, 1.0])),
    "body-short": lambda f: _with_weights(f, _weights_bytes()[:-8]),
    "nan-weight": lambda f: _with_weights(f, _nan_weight()),
    "not-base64": lambda f: {**f, "weights_base64": "%%%not base64%%%"},
    "hash-not-hex": lambda f: {**f, "weights_sha256": "x" * 64},
    "weights-a-number": lambda f: {**f, "weights_base64": 12},
    "epochs-text": lambda f: {**f, "epochs": "30"},
}


@pytest.mark.parametrize("case", list(KALMANNET_FIT_TAMPERED))
def test_a_tampered_kalmannet_fit_cache_is_refused(tmp_path, case):
    from anfekf_bench.filters.kalmannet_net import fitted_weights_problem
    from anfekf_bench.outputs import CachedFitRefused, read_cached_fit, write_fit

    path = tmp_path / "fit-0123456789abcdef.json"
    write_fit(path, "0123456789abcdef", KALMANNET_FIT_TAMPERED[case](_kalmannet_fit()))
    with pytest.warns(CachedFitRefused, match="fitted again"):
        found = read_cached_fit(path, "0123456789abcdef", lambda f: fitted_weights_problem(f, 4))
    assert found is None


def test_an_intact_kalmannet_fit_cache_gives_its_weights(tmp_path, monkeypatch):
    import base64

    import numpy as np

    from anfekf_bench.filters import kalmannet
    from anfekf_bench.outputs import read_cached_fit, write_fit

    path = tmp_path / "fit-0123456789abcdef.json"
    fitted = _kalmannet_fit()
    write_fit(path, "0123456789abcdef", fitted)
    monkeypatch.setattr(kalmannet, "torch_available", lambda: True)  # a spec without PyTorch
    spec = kalmannet.KalmanNetSpec(name="k", kind="kalmannet", hidden_size=4)
    found = read_cached_fit(path, "0123456789abcdef", spec.fit_problem)
    assert found == fitted
    weights = spec.with_fit(found).trained_weights
    original = kalmannet.KalmanNetWeights.from_bytes(base64.b64decode(fitted["weights_base64"]))
    for name, array in original.arrays.items():
        np.testing.assert_array_equal(weights.arrays[name], array)
    other = kalmannet.KalmanNetSpec(name="k", kind="kalmannet", hidden_size=8)
    assert "hidden_size 4, not 8" in other.fit_problem(found)


def test_weights_of_another_system_still_round_trip():
    """`from_bytes` checks what any network's file must hold; the robot's shapes are checked
    only for a fit (kalmannet_train trains linear systems' networks too)."""
    import numpy as np

    from anfekf_bench.filters.kalmannet_net import NET_ARRAYS, KalmanNetWeights

    rng = np.random.default_rng(0)
    arrays = {name: rng.normal(size=(3, 5) if "weight" in name else 3) for name in NET_ARRAYS}
    w = KalmanNetWeights(arrays, np.ones(2), np.ones(4), 1.0, 3)
    back = KalmanNetWeights.from_bytes(w.to_bytes())
    assert back.to_bytes() == w.to_bytes()


# --------------------------------------------------------------------------------------------
# Training runs in the memory and time estimate


def _training_plan(tmp_path: Path, training_runs: int, jobs: int = 1, **overrides):
    from .conftest import small_scenario, write_scenario

    filters = [{"name": "ekf", "kind": "ekf"}, {"name": "tuned", "kind": "ekf-tuned"}]
    doc = small_scenario(
        name="trained", runs=2, jobs=jobs, record_every=8, training={"runs": training_runs},
        **{"filters": filters, **overrides},
    )  # fmt: skip
    path = write_scenario(tmp_path / "trained.yaml", doc)
    return path, make_plan(*load_scenario(path), None, None, None)


def test_training_runs_beyond_the_memory_are_refused_before_any_work(tmp_path, monkeypatch):
    """`training: {runs: 10000}` with ekf-tuned ended in MemoryError under a memory limit: the
    estimate now counts the training set (here 10,000 runs of ~770 steps: ~1.7 GB)."""
    from anfekf_bench import experiment
    from anfekf_bench.experiment import PlanError

    monkeypatch.setattr(experiment, "machine_memory", lambda: 2 * 2**30)  # a 2 GB machine
    path, plan = _training_plan(tmp_path, 10_000)
    with pytest.raises(PlanError, match=r"^training\.runs: 10000 training runs") as err:
        check_plan(plan)
    assert "2.0 GB" in str(err.value) and "80%" in str(err.value)
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    line = _one_error_line(result)
    assert "training.runs" in line and str(path) in line
    assert not (tmp_path / "out").exists()
    # the same scenario with the default 20 training runs passes the same check
    check_plan(_training_plan(tmp_path, 20)[1])


def test_the_training_estimate_counts_one_training_set_whatever_the_jobs(tmp_path):
    """A parallel noise fit's starts run on threads that share the training set: more jobs
    need no more memory for it."""
    from anfekf_bench.experiment import training_memory_estimate

    _, alone = _training_plan(tmp_path, 1000, jobs=1)
    _, three = _training_plan(tmp_path, 1000, jobs=8)  # ekf-tuned: 3 starts on 3 threads
    steps = check_plan(alone)
    assert training_memory_estimate(three, steps) == training_memory_estimate(alone, steps) > 0
    _, untrained = _training_plan(tmp_path, 1000, filters=[{"name": "ekf", "kind": "ekf"}])
    assert training_memory_estimate(untrained, steps) == 0


def test_the_estimate_is_of_the_order_of_what_training_takes(tmp_path):
    """Measured here: what 30 more training runs take (simulated runs and the kernel's copy,
    after a warm-up) against what the estimate adds for them: never below, nor far above."""
    import tracemalloc

    from anfekf_bench.experiment import training_memory_estimate
    from anfekf_bench.fitting.simulated import simulate_training

    def used(plan) -> int:
        tracemalloc.start()
        training = simulate_training(plan.scenario, plan.world, plan.seed)
        _ = training.problem
        found = tracemalloc.get_traced_memory()[0]
        tracemalloc.stop()
        return found

    _, few = _training_plan(tmp_path, 10)
    _, many = _training_plan(tmp_path, 40)
    steps = check_plan(few)
    used(few)  # warm-up: compiled kernels, caches
    measured = used(many) - used(few)
    estimated = training_memory_estimate(many, steps) - training_memory_estimate(few, steps)
    assert 0.5 * estimated < measured < estimated, (measured, estimated)


def test_a_long_plan_says_its_estimate_before_it_starts(tmp_path, monkeypatch):
    from anfekf_bench import experiment
    from anfekf_bench.experiment import long_plan_line, seconds_estimate

    from .conftest import small_scenario, write_scenario

    _, long_plan = _training_plan(tmp_path, 10_000, world={})  # the builtin map: 8,778 steps
    long_plan = make_plan(long_plan.scenario, long_plan.world, 5000, None, 2)
    steps = 8778  # check_plan's count for the builtin route
    training, batch = seconds_estimate(long_plan, steps)
    assert training > 600 and batch > 600
    line = long_plan_line(long_plan, steps)
    assert line.startswith("trained: estimated to take about ") and "\n" not in line
    assert "5000 runs x 8778 control steps x 2 filters on 2 workers" in line
    assert "training of tuned on 10000 training runs" in line
    _, short = _training_plan(tmp_path, 3)
    assert long_plan_line(short, check_plan(short)) is None  # seconds: no line
    # Through `anfekf run`: the line comes before the batch starts (threshold lowered)
    monkeypatch.setattr(experiment, "LONG_PLAN_S", 0.0)
    doc = small_scenario(name="quick", runs=2, record_every=8)
    path = write_scenario(tmp_path / "quick.yaml", doc)
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    first = next(i for i, x in enumerate(lines) if x.startswith("quick: estimated to take"))
    started = next(i for i, x in enumerate(lines) if x.startswith("quick: new results"))
    assert first < started
