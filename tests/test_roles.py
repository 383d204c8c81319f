"""Roles on the spec (issue 33): each kind declares what it is in a comparison, every consumer
asks the registry, and no module outside the registry compares a filter kind with a string."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from anfekf_bench.filters.registry import SPEC_BY_KIND, kinds_with_role, role_of, runs_once
from anfekf_bench.filters.spec import ROLES
from anfekf_bench.sources.recorded import REAL_SPECS

PACKAGE = Path(__file__).resolve().parents[1] / "anfekf_bench"


def test_every_kind_declares_a_known_role():
    for kind, cls in SPEC_BY_KIND.items():
        assert cls.role in ROLES, kind
    for cls in REAL_SPECS:
        assert cls.role in ROLES, cls


def test_the_references_and_the_fitted_and_trained_kinds():
    assert kinds_with_role("reference") == ("ekf",)
    assert kinds_with_role("oracle") == ("ekf-oracle",)
    assert set(kinds_with_role("fitted")) == {"ekf-ml", "ekf-tuned", "ekf-aug-calibrated"}
    assert kinds_with_role("trained") == ("kalmannet",)
    assert role_of("anfekf") == "adaptive" and role_of("custom") == "adaptive"
    assert role_of("no-such-kind") is None
    with pytest.raises(ValueError, match="roles are"):
        kinds_with_role("referee")


def test_only_filters_without_an_assumed_noise_run_once():
    once = {k for k, cls in SPEC_BY_KIND.items() if cls.role in ("fitted", "trained", "oracle")}
    for kind in once:
        spec = SPEC_BY_KIND[kind].model_construct(name=kind, kind=kind)
        assert runs_once(spec), kind
    for kind in set(SPEC_BY_KIND) - once:
        spec = SPEC_BY_KIND[kind].model_construct(name=kind, kind=kind)
        assert not runs_once(spec), kind


# `x.kind == "ekf"`, `kind != 'imm'`, `kind in ("mmae", "imm")`: a kind named by a string.
KIND_TEST = re.compile(
    r"""kind\s*(?:==|!=|(?:not\s+)?in)\s*[\(\[\{]?\s*(["'][^"']+["'](?:\s*,\s*["'][^"']+["'])*)"""
)


def kind_comparisons(source: str) -> list[str]:
    """The registered filter kinds `source` compares a `kind` with, one entry per occurrence."""
    found = []
    for match in KIND_TEST.finditer(source):
        for literal in re.findall(r"""["']([^"']+)["']""", match.group(1)):
            if literal in SPEC_BY_KIND:
                found.append(literal)
    return found


def test_the_finder_sees_each_form_of_a_kind_comparison():
    src = 'a.kind == "ekf-oracle"\nkind in ("mmae", "imm")\nb.kind != \'ekf\'\nx.kind == "dask"'
    assert kind_comparisons(src) == ["ekf-oracle", "mmae", "imm", "ekf"]


def test_no_module_outside_the_registry_compares_a_filter_kind_with_a_string():
    offenders = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        if path == PACKAGE / "filters" / "registry.py":
            continue
        found = kind_comparisons(path.read_text(encoding="utf-8"))
        if found:
            offenders[str(path.relative_to(PACKAGE))] = found
    assert offenders == {}


def test_comparison_rank_orders_a_group_by_role():
    """The overview's order within a scenario: the reference first, the paper's ANFEKF next,
    every other kind, the oracle last (registry.comparison_rank, not a list of kind strings)."""
    from anfekf_bench.filters.registry import comparison_rank

    ranks = {kind: comparison_rank(kind) for kind in SPEC_BY_KIND}
    assert [k for k, r in ranks.items() if r == 0] == list(kinds_with_role("reference"))
    assert [k for k, r in ranks.items() if r == 3] == list(kinds_with_role("oracle"))
    assert [k for k, r in ranks.items() if r == 1] == ["anfekf"]
    assert comparison_rank("no-such-kind") == 2
