"""Sweeps (SPEC 10): grid expansion, path validation, ordering, paired cells, resume."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from anfekf_bench.config import ScenarioError
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.report.document import Document, to_markdown
from anfekf_bench.report.plots import FigureSaver
from anfekf_bench.report.sweep import breakdown_range, read_sweep, section
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.storage import MANIFEST_FILE
from anfekf_bench.sweeps import (
    CELLS_DIR,
    SWEEP_FILE,
    cell_plans,
    expand,
    run_sweep,
)

from .conftest import small_scenario, write_scenario

FILTERS = [
    {"name": "ekf", "kind": "ekf"},
    {"name": "anfekf", "kind": "anfekf", "window": 5},
    {"name": "ekf-oracle", "kind": "ekf-oracle"},
]


def sweep_doc(axes: list[dict], runs: int = 2) -> dict:
    doc = small_scenario(name="sw", runs=runs, jobs=1)
    doc["filter_noise"] = {}  # the true noise: factor 1 is the oracle's setting
    doc["filters"] = FILTERS
    doc["sweep"] = {"axes": axes}
    return doc


def load(tmp_path, doc):
    path = write_scenario(tmp_path / "sweep.yaml", doc)
    scenario, _ = load_scenario(path)
    return scenario, path


def test_a_two_axis_grid_expands_to_every_cell_with_the_values_set(tmp_path):
    scenario, path = load(
        tmp_path,
        sweep_doc(
            [
                {"field": "filter_noise.sigma_range", "values": [0.05, 0.5, 2.0]},
                {"scale": "Qu", "factors": {"start": 0.1, "stop": 10, "num": 3}},
            ]
        ),  # fmt: skip
    )
    cells = expand(scenario, path)
    assert len(cells) == 9
    assert [c.name for c in cells[:2]] == ["cell-000", "cell-001"]
    assert cells[1].coords == pytest.approx({"filter_noise.sigma_range": 0.05, "Qu_factor": 1.0})
    base = scenario.filter_noise
    for cell in cells:
        noise = cell.scenario.filter_noise
        assert noise.sigma_range == cell.coords["filter_noise.sigma_range"]
        factor = cell.coords["Qu_factor"]
        assert noise.sigma_v == pytest.approx(base.sigma_v * math.sqrt(factor), rel=1e-12)
        assert noise.sigma_gamma_deg == pytest.approx(base.sigma_gamma_deg * math.sqrt(factor))
        assert noise.sigma_bearing_deg == base.sigma_bearing_deg
        assert cell.scenario.seed == scenario.seed, "every cell has the scenario's seed"
        assert cell.scenario.sweep is None
    assert sorted({c.coords["Qu_factor"] for c in cells}) == pytest.approx([0.1, 1.0, 10.0])


BAD_AXES = {
    # id: (axes, expected message part)
    "no-such-field": (
        [{"field": "filter_noise.sigma_rnage", "values": [1.0]}],
        "sweep.axes.0.field: filter_noise.sigma_rnage: no field filter_noise.sigma_rnage",
    ),
    "index-out-of-range": (
        [{"field": "filters.7.window", "values": [5]}],
        "filters.7 is not an index of a list of 3",
    ),
    "a-block-not-a-value": ([{"field": "world", "values": [1.0]}], "is a block, not a value"),
    "cell-invalid": (
        [{"field": "filter_noise.sigma_range", "values": [0.1, -1.0]}],
        "sweep cell 1 (filter_noise.sigma_range = -1)",
    ),
    "field-of-the-wrong-filter": (
        [{"field": "filters.0.window", "values": [5]}],
        "no field filters.0.window (there: kind, name)",
    ),
}


@pytest.mark.parametrize("axes, message", BAD_AXES.values(), ids=BAD_AXES.keys())
def test_a_bad_axis_is_one_line_naming_it(tmp_path, axes, message):
    scenario, path = load(tmp_path, sweep_doc(axes))
    with pytest.raises(ScenarioError) as err:
        expand(scenario, path)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_axis_rules_are_validated_with_the_scenario(tmp_path):
    for axes, message in (
        ([{"field": "p0", "scale": "R", "values": [1.0]}], "exactly one of field or scale"),
        ([{"scale": "R"}], "exactly one of values or factors"),
        ([{"scale": "R", "values": [1.0, 1.0]}], "lists a value twice"),
        ([{"scale": "R", "values": [1.0]}, {"scale": "R", "values": [2.0]}], "same field"),
    ):
        path = write_scenario(tmp_path / "bad.yaml", sweep_doc(axes))
        with pytest.raises(ScenarioError, match=message):
            load_scenario(path)


def _sweep(tmp_path, doc, out, **kw):
    scenario, path = load(tmp_path, doc)
    cells = expand(scenario, path)
    plans = cell_plans(cells, runs=None, seed=None, jobs=None)
    return run_sweep(scenario.name, scenario.sweep.axes, cells, plans, out, **kw)


def test_cells_are_ordered_naturally_and_equal_the_scenario_written_by_hand(tmp_path):
    axes = [{"scale": "R", "values": [10.0, 0.1, 2.0, 1.0]}]  # written out of order
    table, target = _sweep(tmp_path, sweep_doc(axes), tmp_path / "out")
    assert (target / SWEEP_FILE).is_file() and (target / MANIFEST_FILE).is_file()
    assert list(table["R_factor"].unique()) == [0.1, 1.0, 2.0, 10.0], "numeric order"
    oracle = table[table["filter"] == "ekf-oracle"]
    assert (oracle["rmse_pos_vs_oracle"] == 1.0).all()
    ekf_at_1 = table[(table["filter"] == "ekf") & (table["R_factor"] == 1.0)].iloc[0]
    # R factor 1 is the scenario itself: ekf == oracle when filter and true noise agree.
    assert ekf_at_1["rmse_pos_vs_oracle"] == pytest.approx(1.0, abs=1e-12)

    # The cell at R factor 2, written out by hand, gives the same numbers.
    hand = sweep_doc(axes)
    del hand["sweep"]
    noise = dict(hand.get("filter_noise", {}))
    base = load_scenario(write_scenario(tmp_path / "b.yaml", hand))[0].filter_noise
    noise.update(
        sigma_range=base.sigma_range * math.sqrt(2.0),
        sigma_bearing_deg=base.sigma_bearing_deg * math.sqrt(2.0),
    )
    hand.update(name="hand", filter_noise=noise)
    plan = make_plan(*load_scenario(write_scenario(tmp_path / "hand.yaml", hand)), None, None, 1)
    records, _ = execute(plan, tmp_path / "hand-out")
    by_hand = pd.DataFrame(records).set_index("filter")
    cell = table[table["R_factor"] == 2.0].set_index("filter")
    for metric in ("rmse_pos", "anees", "nees_in_bounds"):
        np.testing.assert_allclose(
            cell[metric].to_numpy(float), by_hand.loc[cell.index, metric].to_numpy(float),
            rtol=1e-12, err_msg=metric,
        )  # fmt: skip


def test_an_interrupted_sweep_resumes_to_the_same_table(tmp_path):
    axes = [{"scale": "Qu", "values": [0.5, 2.0]}, {"scale": "R", "values": [0.5, 2.0]}]
    doc = sweep_doc(axes)
    reference, _ = _sweep(tmp_path, doc, tmp_path / "ref")

    seen = {"n": 0}

    def stop_mid_sweep(_result: dict) -> None:
        seen["n"] += 1
        if seen["n"] == 5:  # cell 2, run 0 saved
            raise KeyboardInterrupt

    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        _sweep(tmp_path, doc, out, on_result=stop_mid_sweep)
    cells = out / "sw" / CELLS_DIR
    assert (cells / "cell-001" / MANIFEST_FILE).is_file()
    assert not (cells / "cell-002" / MANIFEST_FILE).exists()
    assert not (out / "sw" / SWEEP_FILE).exists()

    said = []
    table, target = _sweep(tmp_path, doc, out, on_cell=lambda cell, what: said.append(what))
    assert said[:2] == ["complete already: reused"] * 2 and said[2:] == ["running"] * 2
    pd.testing.assert_frame_equal(table, reference)


def test_breakdown_range_around_factor_one():
    table = pd.DataFrame(
        {
            "filter": ["a"] * 5 + ["b"] * 5,
            "R_factor": [0.1, 0.3, 1.0, 3.0, 10.0] * 2,
            "rmse_pos_vs_oracle": [3.0, 1.2, 1.0, 1.4, 2.0, 2.0, 2.0, 1.6, 1.0, 1.0],
        }
    )
    found = breakdown_range(table, "R_factor", within=1.5)
    assert found["a"] == (0.3, 3.0)
    assert all(math.isnan(v) for v in found["b"]), "b is off even without mismatch"


@pytest.mark.parametrize("n_axes", [1, 2])
def test_the_sweep_report_draws_lines_or_heatmaps(tmp_path, n_axes):
    axes = [{"scale": "R", "values": [0.5, 1.0, 4.0]}, {"scale": "Qu", "values": [0.5, 2.0]}]
    _, target = _sweep(tmp_path, sweep_doc(axes[:n_axes]), tmp_path / "out")
    save = FigureSaver(tmp_path / "report", html=False)
    (tmp_path / "report").mkdir()
    text = to_markdown(Document("", section(read_sweep(target), save)))
    files = save.files
    assert all(p.is_file() and p.stat().st_size > 5000 for p in files)
    if n_axes == 1:
        assert len(files) == 1 and "Break-down" in text and "| ekf-oracle | 0.5 | 4 |" in text
    else:
        assert len(files) == 4, "one heatmap figure per metric, a panel per filter"
        assert "Break-down" not in text
    assert all(f"({p.name})" in text for p in files), "relative links"
