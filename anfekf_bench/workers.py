"""Local worker processes that end with their parent (every pipeline's joblib pool).

One place starts loky workers for batches, tuning and fitting, so that a killed command never
leaves a worker behind (docs/HARDENING.md).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
import warnings
from collections.abc import Iterator

from joblib import parallel_config

PARENT_POLL_S = 0.2  # how often a worker looks whether its parent is still there [s]


@contextlib.contextmanager
def local_workers() -> Iterator[None]:
    """joblib's loky workers for a batch: each starts by watching this process and ends with it
    (`_watch_parent`), so a killed command leaves no worker behind.

    loky ends a worker whose memory grew by 300 MB (a zoo scenario's steps table read for the
    report) and starts another; if work was waiting it says so in a UserWarning. Nothing is
    lost, so the warning is not passed on to the user."""
    with (
        parallel_config(backend="loky", initializer=_watch_parent, initargs=(os.getpid(),)),
        warnings.catch_warnings(),
    ):
        warnings.filterwarnings(
            "ignore", message="A worker stopped while some jobs were given", category=UserWarning
        )
        yield


def _watch_parent(parent: int) -> None:
    """loky worker initializer: start a daemon thread that ends this worker process when its
    parent `parent` is gone. loky keeps workers for minutes; after a kill -9 of the parent they
    would live on, holding its stdout/stderr open (`anfekf run ... | tee log` would never end).
    Not called with jobs 1 (joblib then runs the batch in the calling process)."""
    if os.getpid() != parent:
        threading.Thread(
            target=_exit_with_parent, args=(parent,), name="anfekf-parent-watch", daemon=True
        ).start()


def _exit_with_parent(parent: int) -> None:
    while True:
        if os.getppid() != parent:  # re-parented: the parent died
            os._exit(1)
        time.sleep(PARENT_POLL_S)
