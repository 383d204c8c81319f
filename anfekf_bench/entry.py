"""The `anfekf` command's entry point: catches Ctrl-C from the first instant.

The command's modules (typer, rich, pandas, pydantic, the filters) take about a second to import;
a Ctrl-C then would print a KeyboardInterrupt traceback. This module imports nothing heavy, so
the handler below is in place before they load. (During a batch, `anfekf run` reports an
interruption itself, saying which runs are saved.)
"""

from __future__ import annotations

import sys

EXIT_INTERRUPTED = 130  # as a shell reports a command ended by SIGINT


def main() -> None:  # pragma: no cover - exercised through a subprocess in the tests
    try:
        from .cli import main as cli_main

        cli_main()
    except KeyboardInterrupt:
        try:
            sys.stderr.write("error: interrupted\n")
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        sys.exit(EXIT_INTERRUPTED)


if __name__ == "__main__":
    main()
