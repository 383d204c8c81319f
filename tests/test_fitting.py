"""The one fitting entry point (anfekf_bench.fitting.fit.fit_specs): every spec that declares a fit
(`fit_sources`, `fit`) is fitted through it on each source's training runs it declares
(simulated training seeds, a recorded log's training segments or other drives, a run's own
innovations), cached by the training runs' fingerprint, refused on a source it does not declare;
and each source's preparation reaches the spec's fit through it."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.filters.registry import SPECS
from anfekf_bench.filters.spec import FIT_SOURCES
from anfekf_bench.fitting import fit as fitting_fit
from anfekf_bench.fitting.fit import FitNotDeclared, fit_specs
from anfekf_bench.fitting.own import fit_on_own_innovations, own_innovations
from anfekf_bench.fitting.recorded import RecordedTraining, tune_segments
from anfekf_bench.fitting.simulated import TRAINING_BRANCH, TrainingSet, fit_filters
from anfekf_bench.sources.recorded import REAL_SPECS, parse_real_scenario

from .conftest import small_scenario
from .test_ekf_ml_real import drive_span

# Every spec class of either scenario schema that declares a fit, with each source it declares
FITTED_CLASSES = list(dict.fromkeys(c for c in (*SPECS, *REAL_SPECS) if c.fit_sources))
DECLARED = [(c, source) for c in FITTED_CLASSES for source in sorted(c.fit_sources)]


def kind_of(cls) -> str:
    return cls.model_fields["kind"].annotation.__args__[0]


# Small settings per kind that make a fit quick (a kind not listed fits with its defaults)
QUICK = {
    "ekf-ml": {"starts": [1.0], "max_evaluations": 12},
    "ekf-tuned": {"starts": [1.0], "max_evaluations": 12},
    "kalmannet": {"epochs": 1, "hidden_size": 4, "validation_runs": 1, "window_s": 20.0},
}


def make_spec(cls):
    if kind_of(cls) == "kalmannet":
        pytest.importorskip("torch")
    quick = {k: v for k, v in QUICK.get(kind_of(cls), {}).items() if k in cls.model_fields}
    return cls(name="fitted", kind=kind_of(cls), **quick)


def simulated_training() -> TrainingSet:
    scenario = parse_scenario(small_scenario(training={"runs": 2}))
    world = resolve_world(scenario.world, ".")
    return TrainingSet(scenario=scenario, world=world, seed=scenario.seed)


def recorded_scenario():
    """Two built-in drives, ekf-tuned on a two-setting grid, ekf-ml with a quick search."""
    return parse_real_scenario({
        "name": "fit", "protocol": "drives", "starts": [1],
        "data": {"kind": "mrclam", "path": "builtin", "drives": ["d6-r2", "d7-r1"]},
        "tuning": {"sigma_v": [0, 1], "sigma_w": [0, 0], "sigma_range": [0, 0],
                   "sigma_bearing": [0, 0], "refine": False},
        "filters": [{"name": "ekf", "kind": "ekf"}, {"name": "ekf-tuned", "kind": "ekf-tuned"},
                    {"name": "ekf-ml", "kind": "ekf-ml", **QUICK["ekf-ml"]}],
    })  # fmt: skip


@pytest.fixture(scope="module")
def spans():
    first = drive_span("d6-r2", 100.0, 160.0)
    second = drive_span("d7-r1", 100.0, 160.0)
    return [first, replace(second, segment=replace(second.segment, index=1))]


def recorded_training(spans) -> RecordedTraining:
    """One fold of one training drive (the first 60 s span), scored whole."""
    return RecordedTraining(
        scenario=recorded_scenario(),
        inputs=spans[:1],
        what="one drive",
        account={"train_drives": ["d6-r2"]},
        data_doc={"drives": ["d6-r2 100-160 s"]},
        drives=True,
    )


def training_runs(source: str, spans):
    """A small set of training runs of each source."""
    if source == "simulated":
        return simulated_training()
    if source == "recorded":
        return recorded_training(spans)
    if source == "own":
        return own_innovations(recorded_scenario(), spans[0])
    raise AssertionError(f"no training runs of source {source!r} in this test: add them")


def test_every_declared_source_is_one_the_fitting_module_supplies():
    assert FITTED_CLASSES, "no spec declares a fit"
    assert {s for c in FITTED_CLASSES for s in c.fit_sources} <= set(FIT_SOURCES)
    declared = {(kind_of(c), s) for c, s in DECLARED}
    # the fits the package has: ekf-ml (simulated, own), ekf-tuned (simulated; recorded: the
    # grid search of the recorded schema's ekf-tuned), kalmannet (simulated, recorded)
    assert {("ekf-ml", "simulated"), ("ekf-ml", "own"), ("ekf-tuned", "simulated"),
            ("ekf-tuned", "recorded"), ("kalmannet", "simulated"),
            ("kalmannet", "recorded")} <= declared  # fmt: skip


@pytest.mark.parametrize(
    "cls, source", DECLARED, ids=[f"{kind_of(c)}-{c.__name__}-{s}" for c, s in DECLARED]
)
def test_each_declared_fit_goes_through_the_one_entry_point(cls, source, spans, tmp_path):
    spec = make_spec(cls)
    training = training_runs(source, spans)
    first = fit_specs([(spec, training)], tmp_path)[0]
    assert not first.cached and len(first.fingerprint) == 16
    assert training.fit_problem(spec)(first.fitted) is None
    assert json.dumps(first.fitted)
    assert (tmp_path / f"fit-{first.fingerprint}.json").is_file()
    # read back from the cache, not fitted again
    again = fit_specs([(spec, training)], tmp_path)[0]
    assert again.cached and again.fitted == first.fitted
    # without a cache: fitted again, the same values but for the time it took
    fresh = fit_specs([(spec, training)], None)[0]
    drop = {"seconds", "training_time_s", "training_cpu_s"}
    assert {k: v for k, v in fresh.fitted.items() if k not in drop} == {
        k: v for k, v in first.fitted.items() if k not in drop
    }
    record = first.record(spec, training)
    assert record["kind"] == spec.kind and record["fingerprint"] == first.fingerprint
    assert set(training.describe()) <= set(record)


UNDECLARED = [(c, s) for c in FITTED_CLASSES for s in FIT_SOURCES if s not in c.fit_sources]


@pytest.mark.parametrize(
    "cls, source", UNDECLARED, ids=[f"{kind_of(c)}-{c.__name__}-{s}" for c, s in UNDECLARED]
)
def test_a_source_a_spec_does_not_declare_is_refused(cls, source, spans):
    spec = make_spec(cls)
    training = training_runs(source, spans)
    with pytest.raises(FitNotDeclared, match=rf"declares no fit on '{source}' training runs"):
        fit_specs([(spec, training)], None)


@pytest.fixture
def through(monkeypatch):
    """The (kind, source) of every fit that reaches a spec's `fit` through `fit_specs`."""
    seen = []
    real = fitting_fit._fit

    def spy(spec, training):
        seen.append((spec.kind, training.source))
        return real(spec, training)

    monkeypatch.setattr(fitting_fit, "_fit", spy)
    return seen


def test_each_source_preparation_fits_through_the_entry_point(through, spans, tmp_path):
    """Simulated (fit_filters), recorded training segments (tune_segments) and own innovations
    (fit_on_own_innovations) reach the specs' fits only through fit_specs."""
    from anfekf_bench.experiment import make_plan

    doc = small_scenario(training={"runs": 2}, filters=[
        {"name": "ekf", "kind": "ekf"},
        {"name": "ml", "kind": "ekf-ml", **QUICK["ekf-ml"]},
        {"name": "tuned", "kind": "ekf-tuned", **QUICK["ekf-tuned"]},
    ])  # fmt: skip
    scenario = parse_scenario(doc)
    fits = fit_filters(make_plan(scenario, resolve_world(scenario.world, "."), 1, None, 1), None)
    assert through == [("ekf-ml", "simulated"), ("ekf-tuned", "simulated")]
    assert fits.records["ml"]["training_seed_branch"] == [scenario.seed, TRAINING_BRANCH]
    through.clear()
    recorded = recorded_scenario()
    rec = type("Rec", (), {"train_segments": [s.segment for s in spans], "digest": "fixed"})
    tuned = tune_segments(recorded, rec, spans)
    assert tuned["settings"] == 2 and through == [("ekf-tuned", "recorded")]
    through.clear()
    noise, record = fit_on_own_innovations(recorded, spans, ["a", "b"], tmp_path)
    assert through == [("ekf-ml", "own"), ("ekf-ml", "own")] and record["fitted_now"] == 2
    assert sorted(noise) == [0, 1]


def test_own_fits_on_threads_are_the_fits_of_one_thread(spans):
    """Each run's own-innovation fit runs on a thread of `jobs` (fits_in_threads): the same
    values, in the same order, as one after the other."""
    recorded = recorded_scenario()
    one = fit_on_own_innovations(recorded, spans, ["a", "b"], None, 1)
    two = fit_on_own_innovations(recorded, spans, ["a", "b"], None, 2)

    def timeless(doc):  # what a fit found, without what it took
        if isinstance(doc, dict):
            return {k: timeless(v) for k, v in doc.items() if k != "seconds"}
        return [timeless(v) for v in doc] if isinstance(doc, (list, tuple)) else doc

    assert timeless(one) == timeless(two) and len(one[0]) == 2


def test_a_spec_fitted_on_simulated_training_runs_declares_that_source():
    """`fitted_on_training` (a spec the simulated path fits and hands out with `with_fit`) and
    the declared "simulated" source say the same for every kind."""
    for cls in dict.fromkeys((*SPECS, *REAL_SPECS)):
        assert cls.fitted_on_training == ("simulated" in cls.fit_sources), cls.__name__


def test_drive_folds_never_train_on_the_drives_they_score(through, spans, monkeypatch):
    """Protocol drives: ekf-tuned is fitted (through fit_specs) once per fold on the other
    datasets' drives; the values a drive runs with never saw it. The in-dataset tunings (the
    audit's comparison) are fitted too, and used for nothing else."""
    from types import SimpleNamespace

    from anfekf_bench.fitting import recorded as fitting_recorded
    from anfekf_bench.fitting.recorded import tune_drives
    from anfekf_bench.sources import mrclam as m

    folds = []
    real = fitting_recorded.fit_specs

    def spy(requests, cache_dir, jobs=1):
        folds.extend(tuple(training.account["train_drives"]) for _, training in requests)
        return real(requests, cache_dir, jobs)

    monkeypatch.setattr(fitting_recorded, "fit_specs", spy)
    ids = ["d6-r2", "d7-r1"]
    world = SimpleNamespace(drives=[
        SimpleNamespace(id=i, dataset=m.drive_dataset(i), log=m.load_drive(i)) for i in ids
    ])  # fmt: skip
    tuned_for, doc = tune_drives(recorded_scenario(), dict(zip(ids, spans, strict=True)), world)
    assert through == [("ekf-tuned", "recorded")] * 2 and sorted(folds) == [("d6-r2",), ("d7-r1",)]
    for drive in ids:
        assert drive not in tuned_for[drive]["train_drives"]
    assert {r["drive"]: r["tuned_on"] for r in doc["per_drive"]} == {
        "d6-r2": ["d7-r1"],
        "d7-r1": ["d6-r2"],
    }
