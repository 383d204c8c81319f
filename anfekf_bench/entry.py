"""The `anfekf` command's entry point: catches Ctrl-C from the first instant.

The command's modules (typer, rich, pandas, pydantic, the filters) take about a second to import;
a Ctrl-C then would print a KeyboardInterrupt traceback. This module imports nothing heavy, so
the handler below is in place before they load. (During a batch, `anfekf run` reports an
interruption itself, saying which runs are saved.)

A Ctrl-C that lands while a compiled extension initialises does not always arrive as a
KeyboardInterrupt: pybind11 modules (scipy's HiGHS among them) turn it into
`ImportError: initialization failed` raised from it, so the interruption is looked for along the
exception's chain too.

A Ctrl-C can also land inside a callback the interpreter runs for itself (a weak reference's, as
the import system's module locks use): Python then prints "Exception ignored in ..." with a
traceback and drops the interruption, so the command would go on. `_redeliver_interrupts` makes
such a KeyboardInterrupt arrive again in the main thread, where it is reported as any other.

SIGTERM and SIGHUP stop the command as a Ctrl-C does (`signals.py`), from the first instant too.
"""

from __future__ import annotations

import sys


def _report_interrupt(exc: KeyboardInterrupt) -> None:
    from .signals import exit_code, stopped_by

    try:
        sys.stderr.write(f"error: {stopped_by(exc)}\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    sys.exit(exit_code(exc))


def _redeliver_interrupts() -> None:
    """Install an unraisable-exception hook that hands a swallowed Ctrl-C (or SIGTERM, SIGHUP)
    back to the main thread.

    The hook itself must not be interrupted: a KeyboardInterrupt raised there is "ignored" again.
    So a bare thread (which the hook need not wait for) sends the signal again to the main thread
    a moment after the hook has returned; a real signal also wakes a main thread blocked in a
    system call.
    """
    import _thread
    import signal
    import time

    from .signals import rearm

    main_thread = _thread.get_ident()
    previous = sys.unraisablehook

    def send_signal(signum: int) -> None:
        time.sleep(0.02)
        signal.pthread_kill(main_thread, signum)

    def hook(unraisable) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            # a swallowed SIGTERM or SIGHUP comes again as itself (its one-shot handler re-armed)
            signum = getattr(unraisable.exc_value, "signum", signal.SIGINT)
            rearm(signum)
            try:
                _thread.start_new_thread(send_signal, (signum,))
            except RuntimeError:  # the interpreter is shutting down: nothing left to stop
                pass
            return
        previous(unraisable)

    sys.unraisablehook = hook


def main() -> None:  # pragma: no cover - exercised through a subprocess in the tests
    from .signals import stop_on_termination

    _redeliver_interrupts()
    stop_on_termination()
    try:
        from .cli import main as cli_main

        cli_main()
    except KeyboardInterrupt as exc:
        _report_interrupt(exc)
    except Exception as exc:
        from .signals import interrupt_behind

        found = interrupt_behind(exc)
        if found is not None:
            _report_interrupt(found)
        raise


if __name__ == "__main__":
    main()
