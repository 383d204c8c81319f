"""The README's reference tables are generated from the models (anfekf_bench.docgen) and must
match them: a new scenario key, filter kind or parameter, or a changed default, fails here until
`make readme` rewrites the tables."""

from __future__ import annotations

from pathlib import Path

from anfekf_bench import docgen
from anfekf_bench.config import Scenario
from anfekf_bench.filters.registry import SPEC_BY_KIND

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_tables_match_the_models():
    text = README.read_text(encoding="utf-8")
    assert docgen.render(text) == text, "README tables are out of date: run `make readme`"


def test_every_field_has_a_meaning():
    assert docgen.undocumented() == []


def test_the_tables_name_every_key_kind_and_parameter_with_its_default():
    text = README.read_text(encoding="utf-8")
    for name in Scenario.model_fields:
        assert f"| `{name}` |" in text, name
    # The defaults the issue names, as a user reads them.
    for row in ("| `runs` | integer >= 1 | `50` |", "| `seed` | integer >= 0 | `0` |",
                "| `record_every` | integer >= 1 | `1` |", "| `engine` |", "| `steps_table` |",
                "| `claims` |", "| `compare` |",
                "| `filters` | list of mapping | `[{name: ekf, kind: ekf}]` |"):  # fmt: skip
        assert row in text, row
    for kind, spec in SPEC_BY_KIND.items():
        assert f"**`{kind}`**" in text, kind
        for name, field in spec.model_fields.items():
            if name not in ("name", "kind"):
                assert f"| `{field.alias or name}` |" in text, (kind, name)
    assert "| `window` | integer >= 2 | `20` |" in text  # an ANFEKF hyper-parameter


def test_docgen_check_command(tmp_path, capsys):
    copy = tmp_path / "README.md"
    copy.write_text(README.read_text(encoding="utf-8"), encoding="utf-8")
    assert docgen.main([str(copy), "--check"]) == 0
    stale = copy.read_text(encoding="utf-8").replace("| `runs` | integer >= 1 | `50` |", "| x |")
    copy.write_text(stale, encoding="utf-8")
    assert docgen.main([str(copy), "--check"]) == 1
    assert "make readme" in capsys.readouterr().out
    assert docgen.main([str(copy)]) == 0
    assert docgen.main([str(copy), "--check"]) == 0
