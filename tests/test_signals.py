"""SIGTERM and SIGHUP stop the command as a Ctrl-C does (anfekf_bench/signals.py); the
subprocess tests in tests/test_interrupt.py send them to a running batch."""

from __future__ import annotations

import signal

import pytest

from anfekf_bench import signals


@pytest.fixture
def handlers():
    saved = {sig: signal.getsignal(sig) for sig in signals.TERMINATING}
    yield
    for sig, handler in saved.items():
        signal.signal(sig, handler)


def test_sigterm_raises_terminated_once_and_an_ignored_sighup_stays_ignored(handlers) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as `nohup` starts a command
    signals.stop_on_termination()
    assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    with pytest.raises(signals.Terminated) as caught:
        signal.raise_signal(signal.SIGTERM)
    assert isinstance(caught.value, KeyboardInterrupt), "every Ctrl-C path handles it"
    assert caught.value.signum == signal.SIGTERM
    for sig in signals.TERMINATING:  # a second request does not cut the clean-up short
        assert signal.getsignal(sig) is signal.SIG_IGN
    signal.raise_signal(signal.SIGTERM)  # ignored: nothing raised


def test_exit_code_and_wording_follow_the_signal() -> None:
    assert signals.exit_code(KeyboardInterrupt()) == 130
    assert signals.exit_code(signals.Terminated(signal.SIGTERM)) == 143
    assert signals.exit_code(signals.Terminated(signal.SIGHUP)) == 129
    assert signals.stopped_by(KeyboardInterrupt()) == "interrupted"
    assert signals.stopped_by(signals.Terminated(signal.SIGHUP)) == "terminated (SIGHUP)"
