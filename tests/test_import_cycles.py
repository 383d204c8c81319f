"""No import circles in the package, imports inside functions included (issue 33).

grimp (import-linter's graph) reads every import statement of every module, those inside
functions too; a circle is a strongly connected component of more than one module. The same
count from the command line: `python -m pytest tests/test_import_cycles.py -q`."""

from __future__ import annotations

import grimp


def import_circles(graph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    modules = sorted(graph.modules)
    edges = {m: sorted(graph.find_modules_directly_imported_by(m)) for m in modules}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []
    counter = 0
    for root in modules:
        if root in index:
            continue
        work = [(root, 0)]
        while work:
            node, i = work.pop()
            if i == 0:
                index[node] = low[node] = counter
                counter += 1
                stack.append(node)
                on_stack.add(node)
            if i < len(edges[node]):
                work.append((node, i + 1))
                nxt = edges[node][i]
                if nxt not in index:
                    work.append((nxt, 0))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    circles.append(sorted(component))
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
    return circles


def test_the_cycle_finder_finds_a_circle_through_a_function_level_import():
    graph = grimp.ImportGraph()
    for name in ("a", "a.x", "a.y", "a.z"):
        graph.add_module(name)
    graph.add_import(importer="a.x", imported="a.y")
    graph.add_import(importer="a.y", imported="a.z")
    graph.add_import(importer="a.z", imported="a.x")
    assert import_circles(graph) == [["a.x", "a.y", "a.z"]]
    graph.remove_import(importer="a.z", imported="a.x")
    assert import_circles(graph) == []


def test_the_package_has_no_import_circle():
    graph = grimp.build_graph("anfekf_bench")
    assert import_circles(graph) == []


def test_no_module_is_over_a_thousand_lines():
    """Issue 33: a module that long holds more than one concept; split it (a move commit)."""
    from pathlib import Path

    from anfekf_bench.provenance import source_files

    package = Path(__file__).resolve().parents[1] / "anfekf_bench"
    lengths = {
        str(path.relative_to(package)): len(path.read_text(encoding="utf-8").splitlines())
        for path in source_files(package)  # not the fast engine's generated loops
    }
    assert {name: n for name, n in lengths.items() if n > 1000} == {}
    assert len(lengths) > 50  # the package's modules were found
