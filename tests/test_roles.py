"""Roles on the spec (issue 33): each kind declares what it is in a comparison, every consumer
asks the registry, and no module outside the registry compares a filter kind with a string."""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

from anfekf_bench.filters.registry import (
    SPEC_BY_KIND,
    kind_of,
    kinds_with_role,
    problem_forms,
    role_of,
    runs_once,
)
from anfekf_bench.filters.spec import ROLES, FilterSpec
from anfekf_bench.problems.filters import ProblemFilterSpec
from anfekf_bench.problems.forms import FORMS, FormError, resolve
from anfekf_bench.provenance import source_files
from anfekf_bench.sources.recorded import REAL_SPECS

PACKAGE = Path(__file__).resolve().parents[1] / "anfekf_bench"


def test_every_kind_declares_a_known_role():
    for kind, cls in SPEC_BY_KIND.items():
        assert cls.role in ROLES, kind
    for cls in REAL_SPECS:
        assert cls.role in ROLES, cls
    for cls in FORMS:  # a kind's form on the problems beyond the robot: the registry's role
        spec = cls.model_construct(name="f", kind=kind_of(cls))
        assert spec.role == SPEC_BY_KIND[kind_of(cls)].role in ROLES, cls


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
    for path in source_files(PACKAGE):
        if path == PACKAGE / "filters" / "registry.py":
            continue
        found = kind_comparisons(path.read_text(encoding="utf-8"))
        if found:
            offenders[str(path.relative_to(PACKAGE))] = found
    assert offenders == {}


def _called(func: ast.AST) -> str:
    """The name a call calls (`first_of_kind` of `data.first_of_kind(...)`)."""
    return getattr(func, "id", None) or getattr(func, "attr", None) or ""


def kind_tests(nodes) -> list[str]:
    """Comparisons (`==`, `!=`, `in`) of anything with a registered kind string, and calls of a
    function named after kinds (`first_of_kind(sc, "ekf")`) with one: the forms KIND_TEST
    misses (`name == "ekf-oracle"`, `k == "ekf"`, `"ekf" not in timings`)."""
    found = []

    def kinds_in(node) -> list[str]:
        items = node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set)) else [node]
        strings = [e.value for e in items if isinstance(e, ast.Constant)]
        return [s for s in strings if isinstance(s, str) and s in SPEC_BY_KIND]

    for node in ast.walk(ast.parse(nodes)) if isinstance(nodes, str) else nodes:
        if isinstance(node, ast.Compare):
            found += [k for part in (node.left, *node.comparators) for k in kinds_in(part)]
        elif isinstance(node, ast.Call) and "kind" in _called(node.func).lower():
            found += [k for arg in node.args for k in kinds_in(arg)]
    return found


def test_the_comparison_finder_sees_names_and_keys_compared_with_a_kind():
    src = (
        'name == "ekf-oracle"\nk in ("ekf", "imm")\n"ekf" not in timings\n'
        'first_of_kind(sc, "ekf-oracle")\nx == "dask"\nf(sc, "ekf")'
    )
    assert kind_tests(src) == ["ekf-oracle", "ekf", "imm", "ekf", "ekf-oracle"]


# A value that is not a kind but spells one: vb-imm's `r_rule: sage-husa` (its members' R rule,
# named after the family it borrows).
KNOWN_TESTS = {"filters/vb_bank.py": ["sage-husa"]}


def test_no_module_outside_the_registry_tests_a_name_or_key_against_a_kind():
    found = {path: tests for path, n in package_nodes().items() if (tests := kind_tests(n))}
    assert found == KNOWN_TESTS


def test_comparison_rank_orders_a_group_by_role():
    """The overview's order within a scenario: the reference first, the paper's ANFEKF next,
    every other kind, the oracle last (registry.comparison_rank, not a list of kind strings)."""
    from anfekf_bench.filters.registry import comparison_rank

    ranks = {kind: comparison_rank(kind) for kind in SPEC_BY_KIND}
    assert [k for k, r in ranks.items() if r == 0] == list(kinds_with_role("reference"))
    assert [k for k, r in ranks.items() if r == 3] == list(kinds_with_role("oracle"))
    assert [k for k, r in ranks.items() if r == 1] == ["anfekf"]
    assert comparison_rank("no-such-kind") == 2


# ---------------------------------------------------------------------------------------------
# One list of kinds: the registry's SPECS. A kind's form on the problems beyond the robot is
# named on its spec (`problem_form`) and resolved by problems.forms, never listed again.


def _subclasses(cls: type) -> set[type]:
    return {cls}.union(*(_subclasses(s) for s in cls.__subclasses__()))


SPEC_NAMES = {c.__name__ for c in _subclasses(FilterSpec) | _subclasses(ProblemFilterSpec)}


@functools.cache
def package_nodes() -> dict[str, list[ast.AST]]:
    """Every module of the package but the registry (path relative to it -> its AST nodes),
    parsed once for the scans below."""
    return {
        str(path.relative_to(PACKAGE)): list(ast.walk(ast.parse(path.read_text(encoding="utf-8"))))
        for path in source_files(PACKAGE)
        if path != PACKAGE / "filters" / "registry.py"
    }


def kind_lists(nodes) -> list[list[str]]:
    """The tuples, lists, sets and dict keys among `nodes` (a source's text, or its AST nodes)
    holding two or more filter kinds: spec classes by name or registered kind strings (a list
    of kinds beside the registry's)."""
    found = []
    for node in ast.walk(ast.parse(nodes)) if isinstance(nodes, str) else nodes:
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            items = node.elts
        elif isinstance(node, ast.Dict):
            items = [k for k in node.keys if k is not None]
        else:
            continue
        names = [e.id for e in items if isinstance(e, ast.Name)]
        strings = [e.value for e in items if isinstance(e, ast.Constant)]
        kinds = [n for n in names if n in SPEC_NAMES] + [s for s in strings if s in SPEC_BY_KIND]
        if len(kinds) >= 2:
            found.append(kinds)
    return found


# Lists of kinds still kept elsewhere, each with why (issue 33 counts them); nothing else may
# add one. bench.py's are its timing bins named after the kinds it times, not a selection.
KNOWN_LISTS = {"bench.py": 3}


def test_the_list_finder_sees_a_second_list_of_kinds():
    second = (
        "PROBLEM_FILTER_SPECS = (EKFSpec, OracleSpec, SageHusaSpec, VBRSpec, ALSSpec, MLSpec,"
        " TunedSpec)\nKINDS = ['ekf', 'vb-r']\nRANK = {'ekf': 0, 'anfekf': 1}\nx = ('ekf', 'dask')"
    )
    assert kind_lists(second) == [
        ["EKFSpec", "OracleSpec", "SageHusaSpec", "VBRSpec", "ALSSpec", "MLSpec", "TunedSpec"],
        ["ekf", "vb-r"],
        ["ekf", "anfekf"],
    ]


def test_no_module_outside_the_registry_keeps_a_list_of_kinds():
    """problems/ included: its schema, docs and tests derive the kinds from the registry."""
    found = {path: len(lists) for path, n in package_nodes().items() if (lists := kind_lists(n))}
    assert found == KNOWN_LISTS


def _declared_kinds() -> dict[str, list[str]]:
    """Registered kind -> every class in the package declaring `kind: Literal[<it>]`, as
    "<module path>:<class>"."""
    out: dict[str, list[str]] = {}
    for path, nodes in package_nodes().items():  # the registry declares no spec class
        for node in nodes:
            if not isinstance(node, ast.ClassDef):
                continue
            for stmt in node.body:
                if (
                    isinstance(stmt, ast.AnnAssign)
                    and getattr(stmt.target, "id", None) == "kind"
                    and isinstance(stmt.annotation, ast.Subscript)
                    and getattr(stmt.annotation.value, "id", None) == "Literal"
                    and isinstance(stmt.annotation.slice, ast.Constant)
                    and stmt.annotation.slice.value in SPEC_BY_KIND
                ):
                    where = f"anfekf_bench/{path.removesuffix('.py')}:{node.name}"
                    out.setdefault(stmt.annotation.slice.value, []).append(where)
    return out


def test_each_kind_is_declared_by_its_spec_and_at_most_one_problem_form():
    """One `ekf-tuned` on each side: the robot's spec in the registry and the form it names; a
    third spec class of a registered kind (as problems.tuned once was beside
    recorded.TunedEKFSpec) is not reachable from the registry and fails here."""

    def where(cls: type) -> str:
        return f"{cls.__module__.replace('.', '/')}:{cls.__name__}"

    expected = {kind: [where(cls)] for kind, cls in SPEC_BY_KIND.items()}
    for cls in FORMS:
        expected[kind_of(cls)].append(where(cls))
    declared = _declared_kinds()
    assert {k: sorted(v) for k, v in declared.items()} == {
        k: sorted(v) for k, v in expected.items() if k in declared
    }
    assert set(declared) == set(SPEC_BY_KIND)


def test_the_problem_kinds_are_the_registry_kinds_beyond_the_robot():
    kinds = [k for k, cls in SPEC_BY_KIND.items() if cls.problems - {"robot"}]
    assert [kind_of(cls) for cls in FORMS] == kinds == [k for k, _ in problem_forms()]
    with pytest.raises(FormError, match="names no problem_form"):
        resolve("ekf", None)
    with pytest.raises(FormError, match="declares kind 'ekf-oracle'"):
        resolve("ekf", "filters:OracleSpec")
    with pytest.raises(FormError, match="not a ProblemFilterSpec"):
        resolve("ekf", "filters:GenericKF")
