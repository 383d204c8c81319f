"""A request to stop (SIGTERM, SIGHUP) answered as a Ctrl-C is.

A batch manager, `docker stop`, `systemd`, `timeout` or a closed terminal ends a command with
SIGTERM or SIGHUP, whose default action kills the process where it stands: the runs a fast batch
holds in memory (`outputs.RunStore`) would be lost, the lock and the staging folder left behind.
`anfekf` raises `Terminated`, a KeyboardInterrupt, in the main thread instead, so every path
that saves and cleans up after a Ctrl-C does so after these too, and the command exits with the
status a shell shows for a process the signal ended (143, 129; it exits with it, it is not
killed by the signal). Only the command installs this, for its own run (`stop_on_termination`,
`restore_termination`): a program that imports the package keeps its own handlers.

Imports nothing heavy (the entry point uses it before the command's modules load).
"""

from __future__ import annotations

import contextlib
import signal
import threading

TERMINATING = (signal.SIGTERM, signal.SIGHUP)
_installed: set[int] = set()  # the signals `stop_on_termination` took over
_deferring = 0  # depth of `deferred` blocks
_pending: list[int] = []  # signals that came during them


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP (`signum`) received: the command stops as after a Ctrl-C."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt (a Ctrl-C, or a `Terminated`) that `exc` is or was raised from (or
    while handling), else None."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _ignore(signum: int, frame) -> None:
    """A request after the first: the clean-up runs once (a SIGKILL still ends the process at
    once). A handler, not SIG_IGN, which the processes started meanwhile (the figure workers)
    would inherit, and then ignore the SIGTERM that stops them."""


def _terminate(signum: int, frame) -> None:
    for sig in _installed:
        signal.signal(sig, _ignore)
    if _deferring:
        _pending.append(signum)
        return
    raise Terminated(signum)


def stop_on_termination() -> None:
    """From now on SIGTERM and SIGHUP raise `Terminated` in the main thread; a signal the process
    was started ignoring (`nohup`) stays ignored. Only in the main thread (where handlers are
    set); elsewhere nothing changes."""
    if not _in_main_thread():
        return
    for sig in TERMINATING:
        if sig in _installed or signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _terminate)
            _installed.add(sig)


def restore_termination() -> None:
    """The default action again for the signals `stop_on_termination` took over: once the
    command's work is done, a request to stop while the interpreter ends (its workers, its
    threads) ends it as before, rather than raise where nothing reports it."""
    if not _in_main_thread():
        return
    for sig in _installed:
        signal.signal(sig, signal.SIG_DFL)
    _installed.clear()


def rearm(signum: int) -> None:
    """`signum` raises `Terminated` again (after the one-shot handler set it aside: a
    `Terminated` an interpreter callback swallowed is delivered anew, entry.py)."""
    if _in_main_thread() and signum in _installed:
        signal.signal(signum, _terminate)


@contextlib.contextmanager
def deferred():
    """Within the block a SIGTERM, SIGHUP or Ctrl-C is held and raised when it ends: for a step
    that must not be cut short (starting worker processes, saving the held runs). In the main
    thread only; elsewhere the block runs as it is."""
    global _deferring
    if not _in_main_thread():
        yield
        return
    ctrl_c: list[int] = []
    previous = signal.getsignal(signal.SIGINT)
    hold_ctrl_c = previous not in (signal.SIG_IGN, None)  # ignored (a background job): it stays so
    if hold_ctrl_c:
        signal.signal(signal.SIGINT, lambda signum, frame: ctrl_c.append(signum))
    _deferring += 1
    try:
        yield
    finally:
        _deferring -= 1
        if hold_ctrl_c:
            signal.signal(signal.SIGINT, previous)
    if _deferring == 0 and _pending:
        raise Terminated(_pending.pop(0))
    if ctrl_c:
        raise KeyboardInterrupt


def exit_code(exc: KeyboardInterrupt) -> int:
    """The status a shell shows for a process that signal ended: 143 (SIGTERM), 129 (SIGHUP),
    130 (Ctrl-C)."""
    return 128 + (exc.signum if isinstance(exc, Terminated) else signal.SIGINT)


def stopped_by(exc: KeyboardInterrupt) -> str:
    """'interrupted' (Ctrl-C), 'terminated (SIGTERM)', 'terminated (SIGHUP)'."""
    if isinstance(exc, Terminated):
        return f"terminated ({signal.Signals(exc.signum).name})"
    return "interrupted"
