"""A report figure turned into its file's bytes, in this process or in worker processes.

A figure is saved with the report's rc settings and without timestamps (`figure_bytes`), so
its file is the same bytes wherever it is drawn. `RenderPool` draws pickled figures in worker
processes while the report builds the next ones: about two thirds of a report's time is
matplotlib's drawing at save time (the layout, the ticks, the PNG), and the figures are
independent.

A worker imports only this module (and matplotlib, numpy and the tiny signals.py): everything a
figure holds by reference (the tick locators and formatters below) is defined here, at module
level, so that a figure pickles and a worker starts in about a second without the package's
scenarios, filters or tables.
"""

from __future__ import annotations

import contextlib
import io
import math
import multiprocessing
import os
import pickle
import signal
import threading
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import matplotlib

matplotlib.use("Agg")  # files only; never open a window

import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.ticker import Locator, MaxNLocator  # noqa: E402

from ..signals import deferred  # noqa: E402

DPI = 110
RC = {
    "font.size": 9,
    "axes.titlesize": 10,
    "legend.fontsize": 8,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "svg.hashsalt": "anfekf-report",  # reproducible SVG ids
}
METADATA = {"png": {}, "svg": {"Date": None}, "pdf": {"CreationDate": None}}


def figure_bytes(fig: Figure, fmt: str = "png", dpi: int = DPI) -> bytes:
    """`fig` saved in format png, svg or pdf, with the report's rc settings and no timestamps."""
    buf = io.BytesIO()
    with matplotlib.rc_context(RC):
        fig.savefig(buf, format=fmt, dpi=dpi, metadata=METADATA.get(fmt, {}))
    return buf.getvalue()


def figure_files(fig: Figure, fmt: str, dpi: int, png_copy: bool) -> tuple[bytes, bytes]:
    """The bytes of `fig`'s file in `fmt`, and a PNG copy where `png_copy` (the HTML shows a PDF
    figure as a PNG), else b""."""
    data = figure_bytes(fig, fmt, dpi)
    return data, (figure_bytes(fig, "png", dpi) if png_copy else b"")


def _render_pickled(blob: bytes, fmt: str, dpi: int, png_copy: bool) -> tuple[bytes, bytes]:
    return figure_files(pickle.loads(blob), fmt, dpi, png_copy)


def _ready() -> None:
    """A task that only starts a worker (its imports run while the report reads its results)."""


def _start_worker(parent: int) -> None:
    """A render worker's start: Ctrl-C at the terminal reaches every process of the command;
    the report's own process answers it (exit 130, one line), so a worker ignores it rather
    than print a traceback, and ends with that process (`workers._watch_parent`)."""
    from ..workers import _watch_parent

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _watch_parent(parent)


class Rendering:
    """One figure being drawn by a `RenderPool`: `result()` gives `figure_files`'s bytes, drawn
    in this process if the pool broke (a worker killed), so a figure is never lost."""

    def __init__(self, future: Future, blob: bytes, fmt: str, dpi: int, png_copy: bool):
        self._future = future
        self._args = (blob, fmt, dpi, png_copy)

    def take_back(self) -> bool:
        """Whether no worker has started this drawing and none will (`result` draws it here)."""
        return self._future.cancel()

    def result(self) -> tuple[bytes, bytes]:
        if self._future.cancelled():
            return _render_pickled(*self._args)
        try:
            return self._future.result()
        except BrokenProcessPool:
            return _render_pickled(*self._args)


@contextlib.contextmanager
def _sigint_held():
    """Within the block, SIGINT is ignored by the processes started here and held for this one
    (blocked: Linux keeps a blocked signal pending even while it is ignored, and delivers it
    to the handler restored at the end). Only in the main thread, where handlers are set."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not (
        threading.main_thread()
    ):
        yield
        return
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            yield
        finally:
            signal.signal(signal.SIGINT, handler)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


class RenderPool:
    """`workers` processes that save pickled figures (`submit`), started at once so that their
    imports overlap the caller's work. Each worker ignores Ctrl-C and ends with this process
    (`_start_worker`)."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.broken = False
        # The workers start with Ctrl-C ignored (an ignored signal stays ignored through fork
        # and exec, and Python then installs no handler of its own): one that arrives while a
        # worker imports must not print its traceback. Here it waits, blocked, meanwhile.
        # A SIGTERM meanwhile waits too (signals.deferred), or a worker started before the
        # executor's management thread would be left waiting, and the command with it; once
        # they are all up, it ends them.
        try:
            with deferred(), _sigint_held():
                self._executor = ProcessPoolExecutor(
                    max_workers=workers,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_start_worker,
                    initargs=(os.getpid(),),
                )
                for _ in range(workers):  # spawns them (not forked: pyarrow's threads)
                    self._executor.submit(_ready)
        except KeyboardInterrupt:
            if hasattr(self, "_executor"):
                self.stop()
            raise

    def submit(self, fig: Figure, fmt: str, dpi: int, png_copy: bool) -> Rendering | None:
        """`figure_files` of `fig` in a worker; None where `fig` does not pickle (the caller then
        draws it itself)."""
        try:
            blob = pickle.dumps(fig, protocol=pickle.HIGHEST_PROTOCOL)
        except (pickle.PicklingError, TypeError, AttributeError):
            return None
        try:
            future = self._executor.submit(_render_pickled, blob, fmt, dpi, png_copy)
        except BrokenProcessPool:  # a worker was killed: `render_pool` starts new ones
            self.broken = True
            return None
        return Rendering(future, blob, fmt, dpi, png_copy)

    def stop(self) -> None:
        """End the workers now, drawing or not (Ctrl-C: the command is on its way out and
        would otherwise wait for the drawings they hold)."""
        self.broken = True
        processes = list((getattr(self._executor, "_processes", None) or {}).values())
        # (shutdown forgets the executor's management thread: taken first)
        manager = getattr(self._executor, "_executor_manager_thread", None)
        self._executor.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        # That thread closes its wake-up pipe on its way out, and Python's exit hook writes to
        # the pipe unlocked (concurrent.futures.process on 3.11): a command that ended while
        # the thread was closing it printed "Bad file descriptor" with a traceback after its
        # one line. The thread ends once the workers are gone.
        if manager is not None and manager is not threading.current_thread():
            manager.join(timeout=STOP_WAIT_S)


STOP_WAIT_S = 10.0  # at most, for the management thread of stopped workers (see `stop`)
_POOLS: dict[int, RenderPool] = {}


def figure_workers(jobs: int) -> int:
    """How many worker processes draw a report's figures for `jobs`: min(`jobs`, the CPUs), or
    0 (this process draws them) where that is 1."""
    workers = min(jobs, os.cpu_count() or 1)
    return workers if workers > 1 else 0


def render_pool(workers: int) -> RenderPool | None:
    """The process's pool of `workers` render workers, started on first use and kept for the
    next report (a Python session or a test run draws many; each start costs about a second
    of CPU per worker), replaced if a worker was killed; they end with the process. None for
    no workers, or where no process can be started here (no semaphores, no executable to
    spawn): the report then draws every figure itself."""
    if workers < 1:
        return None
    pool = _POOLS.get(workers)
    if pool is None or pool.broken:
        try:
            pool = RenderPool(workers)
        except (OSError, ImportError, NotImplementedError, BrokenProcessPool):
            _POOLS.pop(workers, None)
            return None
        _POOLS[workers] = pool
    return pool


# ---------------------------------------------------------------------------------------------
# What figures hold by reference: tick locators and formatters (module level: they pickle)


def plain_number(x: float, pos=None) -> str:
    """A tick label in plain notation: 2, 3, 0.05, 1000 (never 2x10^0 or 1e-05)."""
    if not math.isfinite(x) or x <= 0:
        return ""
    return np.format_float_positional(float(f"{x:.3g}"), trim="-")


def plain_power_of_ten(v: float, pos=None) -> str:
    """The tick label of a log10 value: `plain_number` of 10^v (a ratio bar's ticks)."""
    return plain_number(10.0**v)


def general_number(value: float, pos=None) -> str:
    """Tick labels like 0.1, 2, 10 on log axes (not 10^-1)."""
    return f"{value:g}"


class PlainLogLocator(Locator):
    """Ticks for a log axis that are worth labelling in plain numbers, chosen by the view's span:
    under a factor 4, evenly spaced ticks (0.9, 1, 1.1, 1.2); up to 30, 1-2-3-4-6 in each decade;
    up to 1000, 1-2-5; beyond, the powers of ten (every n-th when there are many)."""

    def __call__(self):
        vmin, vmax = self.axis.get_view_interval()
        return self.tick_values(vmin, vmax)

    def tick_values(self, vmin: float, vmax: float) -> np.ndarray:
        vmin, vmax = sorted((vmin, vmax))
        if not (math.isfinite(vmin) and math.isfinite(vmax)) or vmax <= 0:
            return np.array([1.0])
        vmin = vmin if vmin > 0 else vmax / 1e3
        span = vmax / vmin
        if span < 4:
            ticks = MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10]).tick_values(vmin, vmax)
            return ticks[ticks > 0]
        if span <= 30:
            subs = (1, 2, 3, 4, 6)
        elif span <= 1000:
            subs = (1, 2, 5)
        else:
            subs = (1,)
        lo, hi = math.floor(math.log10(vmin)), math.ceil(math.log10(vmax))
        every = max(1, math.ceil((hi - lo) / 8)) if subs == (1,) else 1
        ticks = [m * 10.0**k for k in range(lo, hi + 1, every) for m in subs]
        return np.array([t for t in ticks if vmin / 1.001 <= t <= vmax * 1.001] or [10.0**lo])


# RMSE over the oracle's as a colour: one fixed scale for every heatmap of every report (the
# leaderboard, the sweeps), so a ratio of 1 has one colour wherever it appears. Log scale centred
# on 1 (white); better than the reference in blue (rare: the oracle is the best fixed EKF), worse
# in reds up to 30 x (beyond: the darkest red).
RATIO_MIN, RATIO_MAX = 1 / 1.5, 30.0
# The ratio bar's ticks in the order they are kept when the bar is too short for all of them:
# the reference (1) and the scale's ends first, then the round factors between.
RATIO_TICK_PRIORITY = (1.0, RATIO_MIN, RATIO_MAX, 10.0, 3.0, 2.0, 5.0, 1.5)


def ratio_norm():
    """The colour norm of a ratio's log10: white at 1, fixed ends (never from the data)."""
    from matplotlib.colors import TwoSlopeNorm

    return TwoSlopeNorm(vmin=math.log10(RATIO_MIN), vcenter=0.0, vmax=math.log10(RATIO_MAX))


class RatioBarLocator(Locator):
    """The ratio colour bar's ticks (log10 values): as many of RATIO_TICK_PRIORITY, in that
    order, as fit the bar's drawn height with a label's height between neighbours, so that a
    bar two rows tall shows 0.667, 1, 3, 10, 30 instead of labels that touch."""

    def __init__(self, label_points: float) -> None:
        self.label_points = label_points

    def __call__(self):
        axes = self.axis.axes
        height = axes.bbox.height * 72.0 / axes.figure.dpi  # points, after the layout
        return ratio_bar_ticks(height, self.label_points)


def ratio_bar_ticks(height_points: float, label_points: float) -> list[float]:
    """The log10 ticks of a ratio bar `height_points` tall whose labels are `label_points`."""
    norm = ratio_norm()  # the bar's position of a value: two slopes, 1 in the middle
    kept: list[float] = []
    for tick in RATIO_TICK_PRIORITY:
        value = math.log10(tick)
        gaps = (abs(float(norm(value)) - float(norm(k))) * height_points for k in kept)
        if all(gap >= 1.2 * label_points for gap in gaps):
            kept.append(value)
    return sorted(kept)
