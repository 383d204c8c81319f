"""A request to stop (SIGTERM, SIGHUP) answered as a Ctrl-C is.

A batch manager, `docker stop`, `systemd`, `timeout` or a closed terminal ends a command with
SIGTERM or SIGHUP, whose default action kills the process where it stands: the runs a fast batch
holds in memory (`outputs.RunStore`) would be lost, the lock and the staging folder left behind.
`anfekf` raises `Terminated`, a KeyboardInterrupt, in the main thread instead, so every path
that saves and cleans up after a Ctrl-C does so after these too, and the command ends with the
code a shell gives a process the signal killed (143, 129). Only the command installs it: a
program that imports the package keeps its own handlers.

Imports nothing heavy (the entry point uses it before the command's modules load).
"""

from __future__ import annotations

import signal

TERMINATING = (signal.SIGTERM, signal.SIGHUP)


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP (`signum`) received: the command stops as after a Ctrl-C."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _terminate(signum: int, frame) -> None:
    # The clean-up runs once: a second request while it saves the held runs is ignored (a
    # SIGKILL still ends the process at once).
    for sig in TERMINATING:
        signal.signal(sig, signal.SIG_IGN)
    raise Terminated(signum)


def stop_on_termination() -> None:
    """From now on SIGTERM and SIGHUP raise `Terminated` in the main thread (call it there); a
    signal the process was started ignoring (`nohup`) stays ignored."""
    for sig in TERMINATING:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _terminate)


def exit_code(exc: KeyboardInterrupt) -> int:
    """The code a shell reports for a process that signal ended: 143 (SIGTERM), 129 (SIGHUP),
    130 (Ctrl-C)."""
    return 128 + (exc.signum if isinstance(exc, Terminated) else signal.SIGINT)


def stopped_by(exc: KeyboardInterrupt) -> str:
    """'interrupted' (Ctrl-C), 'terminated (SIGTERM)', 'terminated (SIGHUP)'."""
    if isinstance(exc, Terminated):
        return f"terminated ({signal.Signals(exc.signum).name})"
    return "interrupted"
