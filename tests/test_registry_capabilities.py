"""The registry's kind capabilities (what a kind adapts, which engines run it, its doc), read by
the report's noise figures and `anfekf kinds`: one place, declared on each spec class."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.engines import fast
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.filters import registry
from anfekf_bench.filters.ekf import RobotEKF
from anfekf_bench.filters.spec import AdaptiveSpec, FilterContext
from anfekf_bench.report import plots
from anfekf_bench.report.data import Band
from anfekf_bench.report.report import load_scenario_data
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.storage import read_steps

from .conftest import small_scenario, write_scenario

runner = CliRunner()
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "custom_filter"


def test_every_kind_declares_a_doc_and_what_it_can_adapt():
    for kind in registry.KINDS:
        info = registry.capabilities(kind)
        assert info.doc and "\n" not in info.doc, kind
        assert info.adapts <= {"R", "Q", "P"}, kind
        assert info.engines[0] == "filterpy"
        assert info.default_adapts is None or info.default_adapts <= info.adapts, kind
    assert registry.capabilities("ekf").adapts == frozenset()
    assert registry.capabilities("ekf-oracle").adapts == frozenset()
    assert registry.capabilities("vbakf").adapts == {"R", "P"}


@pytest.mark.parametrize(
    ("record", "adapts"),
    [
        ({"name": "a", "kind": "anfekf"}, {"R"}),  # the default adapt: R
        ({"name": "a", "kind": "anfekf", "adapt": "Q"}, {"Q"}),
        ({"name": "a", "kind": "anfekf", "adapt": "RQ"}, {"R", "Q"}),
        ({"name": "a", "kind": "anfekf", "adaptation": False}, set()),  # then it is the EKF
        ({"name": "a", "kind": "sage-husa", "adapt": "RQ"}, {"R", "Q"}),
        ({"name": "a", "kind": "iae", "adapt": "Q"}, {"Q"}),
        ({"name": "a", "kind": "vb-r"}, {"R"}),
        ({"name": "a", "kind": "vbakf"}, {"R", "P"}),
        ({"name": "a", "kind": "ekf"}, set()),
        ({"name": "a", "kind": "ekf-oracle"}, set()),
    ],
)
def test_what_an_instance_adapts_from_its_spec_or_its_stored_record(record, adapts):
    spec = registry.SPEC_BY_KIND[record["kind"]].model_validate(record)
    assert registry.adapted_noise(spec) == adapts
    # the manifest's stored form gives the same answer without validating anything
    assert registry.adapted_noise(spec.model_dump(mode="json", by_alias=True)) == adapts
    assert registry.adapted_noise(record) == adapts


def test_a_custom_or_unknown_kind_is_left_to_the_recorded_data():
    record = {"name": "mine", "kind": "custom", "class": "not_installed:Anything"}
    assert registry.adapted_noise(record) is None  # no import of the user's class
    assert registry.adapted_noise({"name": "t", "kind": "no-such-kind"}) is None
    # ekf-tuned is a registered kind now (simulated and recorded): a fixed EKF
    assert registry.adapted_noise({"name": "t", "kind": "ekf-tuned"}) == frozenset()


def test_a_new_kind_declares_its_capabilities_on_its_spec_class():
    class SlidingQSpec(AdaptiveSpec):
        """A made-up family that adapts the control noise only."""

        kind: Literal["sliding-q"]
        adapts_noise: ClassVar[frozenset[str]] = frozenset({"Q"})

        def build(self, ctx: FilterContext) -> RobotEKF:
            return RobotEKF(**ctx.kwargs())

    spec = SlidingQSpec(name="s", kind="sliding-q")
    assert registry.adapted_noise(spec) == {"Q"}
    assert registry.adapted_noise(SlidingQSpec(name="s", kind="sliding-q", adaptation=False)) == (
        set()
    )
    assert registry.engines_for(spec) == ("filterpy",)  # the fast engine does not claim it


def test_engines_come_from_each_engine_own_supports():
    for kind in registry.KINDS:
        cls = registry.SPEC_BY_KIND[kind]
        probe = cls.model_construct(name=kind, kind=kind)
        assert ("fast" in registry.capabilities(kind).engines) == fast.supports(probe), kind
    assert "fast" in registry.capabilities("anfekf").engines


def test_anfekf_kinds_lists_every_kind_with_parameters_and_what_it_adapts():
    result = runner.invoke(app, ["kinds"])
    assert result.exit_code == 0, result.output
    for kind in registry.KINDS:
        assert f"\n{kind}: " in "\n" + result.output
    assert "window = 20" in result.output  # a parameter with its default
    vbakf = result.output.split("\nvbakf: ")[1].split("\n")[1]
    assert "R (measurement noise)" in vbakf and "P (covariance)" in vbakf
    ekf = result.output.split("\nekf: ")[0 if result.output.startswith("ekf: ") else 1]
    assert "nothing (fixed noise)" in ekf.split("\n")[1]


# --------------------------------------------------------------------------- the noise figure

ADAPTIVE = {  # name -> what it adapts
    "anfekf": {"R"},
    "sage-husa": {"R"},
    "vb-r": {"R"},
    "iae-q": {"Q"},
    "vbakf": {"R", "P"},
    "nis-scaled": {"R"},  # a custom class: found from its recorded R
}
FIXED = ("ekf", "anfekf-off", "ekf-oracle")


@pytest.fixture(scope="module")
def zoo_result(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("noise")
    sys.path.insert(0, str(EXAMPLE))
    try:
        doc = small_scenario(name="zoo_noise", runs=2, record_every=8)
        doc["filters"] = [
            {"name": "ekf", "kind": "ekf"},
            {"name": "anfekf", "kind": "anfekf", "adapt": "R"},
            {"name": "anfekf-off", "kind": "anfekf", "adaptation": False},
            {"name": "sage-husa", "kind": "sage-husa"},
            {"name": "vb-r", "kind": "vb-r"},
            {"name": "iae-q", "kind": "iae", "adapt": "Q"},
            {"name": "vbakf", "kind": "vbakf"},
            {"name": "nis-scaled", "kind": "custom", "class": "nis_scaled:NisScaledR"},
            {"name": "ekf-oracle", "kind": "ekf-oracle"},
        ]
        scenario, world = load_scenario(write_scenario(root / "zoo_noise.yaml", doc))
        execute(make_plan(scenario, world, None, None, 1), root / "out")
    finally:
        sys.path.remove(str(EXAMPLE))
        sys.modules.pop("nis_scaled", None)
    return root / "out" / "zoo_noise"


def _gids(fig) -> set[str]:
    return {a.get_gid() for ax in fig.axes for a in ax.get_children() if a.get_gid()}


def test_the_noise_figure_has_a_line_for_every_adaptive_filter_and_none_for_fixed_ones(
    zoo_result,
):
    sc = load_scenario_data(zoo_result)
    assert {f.name: set(f.adapts) for f in sc.filters if f.adapts} == ADAPTIVE
    assert sc.adapted_columns == ["R_rr", "R_bb", "Q_vv", "Q_gg"]
    with plots.palette([f.name for f in sc.filters]):
        fig = plots.noise_figure(sc)
    gids = _gids(fig)
    for name, adapts in ADAPTIVE.items():
        for col in ("R_rr", "R_bb", "Q_vv", "Q_gg"):
            assert (f"noise_median/{col}/{name}" in gids) == (col[0] in adapts), (name, col)
    for name in FIXED:
        assert not any(g.endswith(f"/{name}") and g.startswith("noise_median") for g in gids)
    # six adaptive filters: small multiples, one row per family, so no panel holds them all
    rows = plots.noise_groups(sc)
    assert [[f.name for f in row] for row in rows] == [
        ["anfekf"], ["sage-husa"], ["vb-r"], ["iae-q"], ["vbakf"], ["nis-scaled"]
    ]  # fmt: skip
    # the plotted median is the median over runs of steps.parquet's stored value
    steps = read_steps(zoo_result)
    one = steps[steps["filter"] == "sage-husa"].pivot(index="run", columns="step", values="R_rr")
    line = next(
        a for ax in fig.axes for a in ax.get_lines() if a.get_gid() == "noise_median/R_rr/sage-husa"
    )
    np.testing.assert_allclose(line.get_ydata(), np.median(one.to_numpy(), axis=0))
    # every legend is outside the axes: none overlaps a panel
    assert not any(ax.get_legend() for ax in fig.axes)
    assert fig.legends
    # small multiples go without minor ticks (the labels mark 1-2-5 steps); one row keeps them
    shown = [ax for ax in fig.axes if ax.get_visible()]
    assert shown and not any(ax.yaxis.get_minorticklocs().size for ax in shown)
    few = dataclasses.replace(sc, filters=[f for f in sc.filters if f.name in ("ekf", "anfekf")])
    with plots.palette([f.name for f in few.filters]):
        one_row = plots.noise_figure(few)
    assert all(ax.yaxis.get_minorticklocs().size for ax in one_row.axes if ax.get_visible())


def test_the_noise_figure_panels_span_one_time_axis(zoo_result):
    """Every panel of the small multiples spans the same times (as shared axes did), a panel
    whose filter has no finite value included, and only the bottom row labels them."""
    sc = load_scenario_data(zoo_result)
    lost = next(f for f in sc.filters if f.name == "vbakf")
    nan = np.full_like(lost.t, np.nan)
    lost = dataclasses.replace(lost, noise={c: Band(nan, nan, nan, nan) for c in lost.noise})
    filters = [lost if f.name == "vbakf" else f for f in sc.filters]
    for case in (sc, dataclasses.replace(sc, filters=[f for f in filters if f.name != "ekf"])):
        with plots.palette([f.name for f in case.filters]):
            fig = plots.noise_figure(case)
        shown = [ax for ax in fig.axes if ax.get_visible()]
        assert len(shown) > 8 and len({ax.get_xlim() for ax in shown}) == 1
        lo, hi = shown[0].get_xlim()
        assert (
            lo <= sc.filters[0].t[0]
            and hi >= sc.filters[0].t[-1]
            and hi - lo < 1.2 * (sc.filters[0].t[-1] - sc.filters[0].t[0])
        )
        rows = fig.axes[0].get_gridspec().nrows
        for ax in shown:
            labelled = ax.xaxis.get_tick_params()["labelbottom"]
            assert labelled == (ax.get_subplotspec().rowspan.stop == rows), ax.get_title()
