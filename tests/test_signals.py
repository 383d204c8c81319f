"""SIGTERM and SIGHUP stop the command as a Ctrl-C does (anfekf_bench/signals.py); the
subprocess tests in tests/test_interrupt.py send them to a running batch."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from anfekf_bench import signals
from anfekf_bench.cli import OneLineUsageErrors


@pytest.fixture
def handlers():
    saved = {sig: signal.getsignal(sig) for sig in (*signals.TERMINATING, signal.SIGINT)}
    yield
    signals._installed.clear()
    signals._pending.clear()
    for sig, handler in saved.items():
        signal.signal(sig, handler)


def test_sigterm_raises_terminated_once_and_an_ignored_sighup_stays_ignored(handlers) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as `nohup` starts a command
    signals.stop_on_termination()
    assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    assert signal.getsignal(signal.SIGTERM) is signals._terminate, "else the signal kills pytest"
    with pytest.raises(signals.Terminated) as caught:
        signal.raise_signal(signal.SIGTERM)
    assert isinstance(caught.value, KeyboardInterrupt), "every Ctrl-C path handles it"
    assert caught.value.signum == signal.SIGTERM
    # a second request does not cut the clean-up short (not SIG_IGN: children would inherit it)
    assert signal.getsignal(signal.SIGTERM) is signals._ignore
    assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    signal.raise_signal(signal.SIGTERM)  # ignored: nothing raised
    signals.rearm(signal.SIGTERM)  # a swallowed one is delivered again (entry.py)
    with pytest.raises(signals.Terminated):
        signal.raise_signal(signal.SIGTERM)


def test_the_default_action_is_back_when_the_command_is_done(handlers) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signals.stop_on_termination()
    signals.restore_termination()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN, "nohup's choice kept"


def test_off_the_main_thread_nothing_changes(handlers) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    failed = []

    def install() -> None:
        try:
            signals.stop_on_termination()
            with signals.deferred():
                pass
        except Exception as exc:  # pragma: no cover - the failure this test looks for
            failed.append(exc)

    thread = threading.Thread(target=install)
    thread.start()
    thread.join()
    assert failed == [] and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["sigterm", "ctrl-c"])
def test_deferred_holds_a_request_to_the_end_of_its_block(handlers, sig) -> None:
    signals.stop_on_termination()
    signal.signal(signal.SIGINT, signal.default_int_handler)  # SIG_IGN in a background job
    done = []
    with pytest.raises(KeyboardInterrupt) as caught:
        with signals.deferred():
            signal.raise_signal(sig)
            done.append("the block went on")
    assert done == ["the block went on"]
    assert isinstance(caught.value, signals.Terminated) == (sig == signal.SIGTERM)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler, "Ctrl-C's handler back"


def test_deferred_leaves_an_ignored_ctrl_c_ignored(handlers) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a background job of a script starts
    with signals.deferred():
        signal.raise_signal(signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_a_ctrl_c_or_sigterm_click_turns_into_abort_is_said_as_such() -> None:
    app = typer.Typer(cls=OneLineUsageErrors)

    @app.command()
    def stop(how: str) -> None:
        cause = signals.Terminated(signal.SIGTERM) if how == "term" else KeyboardInterrupt()
        raise typer.Abort() from cause

    @app.command()
    def other() -> None:  # two commands: the first argument names one
        raise typer.Abort()

    term = CliRunner().invoke(app, ["stop", "term"])
    assert (term.exit_code, term.stderr) == (143, "error: terminated (SIGTERM)\n")
    ctrl_c = CliRunner().invoke(app, ["stop", "ctrl-c"])
    assert (ctrl_c.exit_code, ctrl_c.stderr) == (130, "error: interrupted\n")
    plain = CliRunner().invoke(app, ["other"])
    assert (plain.exit_code, plain.stderr) == (1, "error: aborted\n")


def test_exit_code_and_wording_follow_the_signal() -> None:
    assert signals.exit_code(KeyboardInterrupt()) == 130
    assert signals.exit_code(signals.Terminated(signal.SIGTERM)) == 143
    assert signals.exit_code(signals.Terminated(signal.SIGHUP)) == 129
    assert signals.stopped_by(KeyboardInterrupt()) == "interrupted"
    assert signals.stopped_by(signals.Terminated(signal.SIGHUP)) == "terminated (SIGHUP)"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc for the workers")
def test_a_sigterm_while_the_figure_workers_start_waits_for_them_then_ends_them(
    handlers, monkeypatch
) -> None:
    """A worker started before the executor's management thread would wait for work forever
    (and the command at its exit with it): the signal waits until every worker is up, then the
    pool ends them and the command stops."""
    from concurrent.futures import ProcessPoolExecutor

    from anfekf_bench.report import render

    signals.stop_on_termination()
    real_submit = ProcessPoolExecutor.submit
    submitted, processes = [], {}

    def submit(self, fn, *args, **kwargs):
        if not submitted:
            signal.raise_signal(signal.SIGTERM)  # as the first worker starts
        submitted.append(fn)
        future = real_submit(self, fn, *args, **kwargs)
        processes.update(self._processes)
        return future

    monkeypatch.setattr(ProcessPoolExecutor, "submit", submit)
    with pytest.raises(signals.Terminated):
        render.RenderPool(2)
    assert submitted == [render._ready, render._ready], "both workers started first"
    assert len(processes) == 2
    # read from /proc: the executor's own thread may reap a worker first (then `is_alive` of
    # this process's handle cannot tell)
    deadline = time.monotonic() + 30
    while running(processes) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert running(processes) == [], "the pool ended its workers"


def running(processes: dict) -> list[int]:
    """The pids of `processes` still running (not ended, not zombies)."""
    alive = []
    for pid in processes:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state not in ("Z", "X"):
            alive.append(pid)
    return alive
