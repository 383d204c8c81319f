"""The `anfekf` command's entry point: catches Ctrl-C from the first instant.

The command's modules (typer, rich, pandas, pydantic, the filters) take about a second to import;
a Ctrl-C then would print a KeyboardInterrupt traceback. This module imports nothing heavy, so
the handler below is in place before they load. (During a batch, `anfekf run` reports an
interruption itself, saying which runs are saved.)

A Ctrl-C that lands while a compiled extension initialises does not always arrive as a
KeyboardInterrupt: pybind11 modules (scipy's HiGHS among them) turn it into
`ImportError: initialization failed` raised from it, so the interruption is looked for along the
exception's chain too.
"""

from __future__ import annotations

import sys

EXIT_INTERRUPTED = 130  # as a shell reports a command ended by SIGINT


def caused_by_interrupt(exc: BaseException) -> bool:
    """Whether `exc` is a KeyboardInterrupt or was raised from (or while handling) one."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


def _report_interrupt() -> None:
    try:
        sys.stderr.write("error: interrupted\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    sys.exit(EXIT_INTERRUPTED)


def main() -> None:  # pragma: no cover - exercised through a subprocess in the tests
    try:
        from .cli import main as cli_main

        cli_main()
    except KeyboardInterrupt:
        _report_interrupt()
    except Exception as exc:
        if caused_by_interrupt(exc):
            _report_interrupt()
        raise


if __name__ == "__main__":
    main()
