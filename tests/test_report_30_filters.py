"""The figures scale to 30 filters (the zoo has 27): read from the artists of a 30-filter
scenario's figures, no legend covers any axes' data area, every legend lies inside the figure, no
two text labels overlap, and no two filters share a colour and line style (one style per filter
across every figure). With 27 filters the NEES plot was ~90 px tall under a 50-entry legend with
its peak labels printed over each other, the RMSE figure's ratio legend covered two thirds of the
data and its bottom legend was cut at both edges, and the changing-noise figure drew `ekf` and
`als` both solid blue.

The scenario is built the way the report reads saved results: a small scenario is run and read
back (`load_scenario_data`), then its filters' series are copied into 30 filters of 10 families
with their own levels (and outlier runs whose NEES leaves the axis)."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_hex

from anfekf_bench.report import plots, summary_figures
from anfekf_bench.report.changing import changes_figure
from anfekf_bench.report.data import Band, Ratio
from anfekf_bench.report.report import load_scenario_data, summary_rows
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.schedule import NoiseSchedule
from anfekf_bench.storage import scenario_dirs

from .conftest import small_scenario, write_scenario
from .test_report_many import assert_readable

FAMILIES = ("ekf", "anfekf", "cm-scale", "sage-husa", "iae", "akhlaghi", "vbakf", "mmae", "als",
            "swvb")  # fmt: skip
pytestmark = pytest.mark.slow  # one small scenario run, then six large figures drawn


def _scaled(band: Band, k: float) -> Band:
    return Band(band.line * k, band.lo * k, band.hi * k, band.median * k)


@pytest.fixture(scope="module")
def zoo30(tmp_path_factory):
    """ScenarioData of 30 filters (29 and the oracle), from a small run read back."""
    from anfekf_bench.api import run

    root = tmp_path_factory.mktemp("zoo30")
    doc = small_scenario(name="zoo30", runs=3, record_every=8)
    doc["filters"] = [{"name": "ekf", "kind": "ekf"},
                      {"name": "anfekf", "kind": "anfekf", "adapt": "R"},
                      {"name": "ekf-oracle", "kind": "ekf-oracle"}]  # fmt: skip
    path = write_scenario(root / "zoo30.yaml", doc)
    load_scenario(path)
    run(path, out=root / "out")
    sc = load_scenario_data(next(iter(scenario_dirs(root / "out"))))
    base = {f.kind: f for f in sc.filters}
    rng = np.random.default_rng(5)
    filters, comparisons = [], {}
    estimate, cov = dict(sc.track.estimate), dict(sc.track.cov)
    for i in range(29):
        family = FAMILIES[i % len(FAMILIES)]
        name = family if i < len(FAMILIES) else f"{family}-{i // len(FAMILIES) + 1}"
        source = base["anfekf"] if i % 2 else base["ekf"]
        k = float(np.exp(rng.uniform(0.0, 2.5)))  # NEES and RMSE levels apart
        outliers = {}
        if i % 7 == 3:  # an outlier run far off the axis: its peak must not print over others
            outliers = {1: source.nees * 1e5}
        summary = {**source.summary, "rmse_pos": source.summary["rmse_pos"] * math.sqrt(k),
                   "anees": source.summary["anees"] * k}  # fmt: skip
        filters.append(dataclasses.replace(
            source, name=name, kind=family, pos=_scaled(source.pos, math.sqrt(k)),
            nees=source.nees * k, nees_median=source.nees_median * k, summary=summary,
            outliers=tuple(outliers), outlier_nees=outliers,
        ))  # fmt: skip
        r = math.sqrt(k)
        comparisons[(name, "ekf-oracle", "rmse_pos")] = Ratio(r, r / 1.05, r * 1.05, 3)
        comparisons[(name, "ekf-oracle", "anees")] = Ratio(k, k / 1.2, k * 1.2, 3)
        estimate[name] = sc.track.estimate[source.name] + 0.01 * i
        cov[name] = sc.track.cov[source.name]
    filters.append(base["ekf-oracle"])
    track = dataclasses.replace(sc.track, estimate=estimate, cov=cov)
    return dataclasses.replace(sc, filters=filters, comparisons=comparisons, track=track)


def _figures(sc):
    rows = summary_rows([sc, dataclasses.replace(sc, name="zoo30_b")])
    schedule = NoiseSchedule.model_validate({"blackouts": [{"start_s": 20, "end_s": 30}]})
    with plots.palette([f.name for f in sc.filters]):
        return {
            "rmse": plots.rmse_figure(sc),
            "nees": plots.nees_figure(sc),
            "noise": plots.noise_figure(sc),
            "map": plots.map_figure(sc),
            "overview": summary_figures.overview_figure(rows),
            "leaderboard": summary_figures.leaderboard_figure(rows),
            "changing": changes_figure(sc, schedule),
        }


@pytest.fixture(scope="module")
def figures(zoo30):
    figs = _figures(zoo30)
    for fig in figs.values():
        FigureCanvasAgg(fig).draw()
    return figs


def _legends(fig) -> list:
    return [*fig.legends, *(ax.get_legend() for ax in fig.axes if ax.get_legend())]


def _data_axes(fig) -> list:
    """The axes that show data (not colour bars)."""
    return [ax for ax in fig.axes if ax.get_visible() and ax.get_label() != "<colorbar>"]


@pytest.mark.parametrize("kind", ["rmse", "nees", "noise", "map", "overview", "leaderboard",
                                  "changing"])  # fmt: skip
def test_no_legend_covers_data_and_every_legend_is_inside_the_figure(figures, kind):
    fig = figures[kind]
    renderer = fig.canvas.get_renderer()
    page = fig.bbox
    for legend in _legends(fig):
        box = legend.get_window_extent(renderer)
        assert page.x0 - 1 <= box.x0 and box.x1 <= page.x1 + 1, f"{kind}: legend cut at a side"
        assert page.y0 - 1 <= box.y0 and box.y1 <= page.y1 + 1, f"{kind}: legend cut top/bottom"
        for ax in _data_axes(fig):
            area = ax.get_window_extent(renderer)
            w = min(box.x1, area.x1) - max(box.x0, area.x0)
            h = min(box.y1, area.y1) - max(box.y0, area.y0)
            assert w <= 1 or h <= 1, f"{kind}: a legend covers the data of {ax.get_title()!r}"


@pytest.mark.parametrize("kind", ["rmse", "nees", "overview", "leaderboard", "changing"])
def test_no_two_labels_overlap_and_none_is_cut(figures, kind):
    assert_readable(figures[kind])


def test_the_nees_figure_is_small_multiples_with_room_for_the_data(figures):
    fig = figures["nees"]
    renderer = fig.canvas.get_renderer()
    panels = _data_axes(fig)
    assert len(panels) >= 8  # 29 filters, at most 4 a panel (and the reference in each)
    for ax in panels:
        assert ax.get_window_extent(renderer).height >= 150  # was ~90 px under a legend
        names = {
            a.get_gid().split("/")[1] for a in ax.lines if (a.get_gid() or "").startswith("nees/")
        }
        assert len(names) <= plots.PANEL_FILTERS + 1
    # an outlier off the axis: a marker at the top, its peak in the legend (no loose text)
    marks = [a for ax in panels for a in ax.lines if (a.get_gid() or "").startswith("nees_off")]
    assert marks and not any(ax.texts for ax in panels)


LINE_GID = re.compile(r"^(rmse_pos|nees|rmse_ratio|map_est|changing_rmse|changing_ratio)/(.+)$")


def test_one_style_per_filter_across_every_figure_and_no_two_alike(figures, zoo30):
    names = [f.name for f in zoo30.filters]
    styles: dict[str, set] = {n: set() for n in names}
    for fig in figures.values():
        for ax in fig.axes:
            for line in ax.lines:
                found = LINE_GID.match(line.get_gid() or "")
                if found and found.group(2) in styles:
                    dashes = line._unscaled_dash_pattern  # the line style, custom dashes too
                    styles[found.group(2)].add((to_hex(line.get_color()), str(dashes)))
    assert all(len(s) == 1 for s in styles.values()), {
        n: s for n, s in styles.items() if len(s) != 1
    }
    pairs = [next(iter(s)) for s in styles.values()]
    assert len(set(pairs)) == len(names) == 30
    # the overview's bars: colour and hatch apart as well
    bars = {}
    for ax in figures["overview"].axes:
        for patch in ax.patches:
            gid = patch.get_gid() or ""
            if gid.startswith("overview_nees_in_bounds/zoo30/"):
                bars[gid.rsplit("/", 1)[1]] = (to_hex(patch.get_facecolor()), patch.get_hatch())
    assert len(bars) == 30 and len(set(bars.values())) == 30
