"""Live progress of a set of tasks (a study's formulations, a check's replicates).

Each task is queued, then running — with phases such as ``compiling`` and ``sampling``
that the running code announces with :func:`report_phase` — then done (with its wall time
and a note such as the sampling rate, :func:`report_note`) or failed.  Two displays show
it: :class:`BarDisplay` (one live line per task, with ``tqdm``) on a terminal and
:class:`LineDisplay` (one plain line per event) otherwise; :func:`task_display` picks one.
:class:`TaskDisplay` itself shows nothing.

The code that runs a task (:func:`kohpymc.execution.run_tasks`) decides where
:func:`report_phase` goes: straight to the display in this process, or as an event from
a Dask worker back to the client.  Outside a task both calls do nothing, so library code
may call them unconditionally.
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import IO, Any

__all__ = [
    "BarDisplay",
    "LineDisplay",
    "TaskDisplay",
    "report_note",
    "report_phase",
    "reporting_to",
    "task_display",
]

#: ``reporter(kind, text)`` of the task running in this context (kind "phase" or "note")
_REPORTER: ContextVar[Callable[[str, str], None] | None] = ContextVar(
    "kohpymc_task_reporter", default=None
)


def report_phase(text: str) -> None:
    """Announce what the running task does now (e.g. ``"compiling"``, ``"sampling"``).

    Does nothing outside a task run by :func:`kohpymc.execution.run_tasks`.

    Examples
    --------
    >>> report_phase("sampling")  # outside a task: nothing happens
    """
    reporter = _REPORTER.get()
    if reporter is not None:
        reporter("phase", text)


def report_note(text: str) -> None:
    """Attach a note to the running task, shown when it is done (e.g. ``"850 draws/s"``).

    Examples
    --------
    >>> report_note("850 draws/s")  # outside a task: nothing happens
    """
    reporter = _REPORTER.get()
    if reporter is not None:
        reporter("note", text)


@contextmanager
def reporting_to(reporter: Callable[[str, str], None]) -> Iterator[None]:
    """Send :func:`report_phase` / :func:`report_note` calls in this block to ``reporter``.

    Examples
    --------
    >>> seen = []
    >>> with reporting_to(lambda kind, text: seen.append((kind, text))):
    ...     report_phase("compiling")
    >>> seen
    [('phase', 'compiling')]
    """
    token = _REPORTER.set(reporter)
    try:
        yield
    finally:
        _REPORTER.reset(token)


class TaskDisplay:
    """The display interface; this base class shows nothing (``--quiet``).

    The methods may be called from another thread than the one that made the display
    (Dask delivers worker events on the client's event-loop thread).

    Examples
    --------
    >>> display = TaskDisplay()
    >>> display.queued(["M0", "M1"]); display.running("M0"); display.done("M0", 1.5)
    >>> display.close()
    """

    def queued(self, keys: Sequence[str]) -> None:
        """The tasks waiting to run, in their order."""

    def running(self, key: str) -> None:
        """``key`` started on a worker (or in this process)."""

    def phase(self, key: str, text: str) -> None:
        """``key`` entered a phase (compiling, sampling, ...)."""

    def note(self, key: str, text: str) -> None:
        """A note on ``key`` to show when it is done (e.g. its sampling rate)."""

    def done(self, key: str, seconds: float) -> None:
        """``key`` finished after ``seconds`` of wall time."""

    def failed(self, key: str, error: str) -> None:
        """``key`` failed with ``error``."""

    def write(self, text: str) -> None:
        """A line of text that is not about one task."""

    def close(self) -> None:
        """No more events."""


class _States:
    """Per-task state shared by the displays: position, phase, start time, note."""

    def __init__(self) -> None:
        self.order: list[str] = []
        self.phase: dict[str, str] = {}
        self.since: dict[str, float] = {}
        self.notes: dict[str, str] = {}

    def add(self, keys: Sequence[str]) -> None:
        for key in keys:
            if key not in self.phase:
                self.order.append(key)
                self.phase[key] = "queued"

    def position(self, key: str) -> str:
        self.add([key])
        return f"[{self.order.index(key) + 1}/{len(self.order)}]"

    def finished_text(self, key: str, seconds: float) -> str:
        note = self.notes.get(key)
        return f"done in {seconds:.1f} s" + (f" ({note})" if note else "")


class LineDisplay(TaskDisplay):
    """One plain line per event, for logs and pipes: ``[2/5] M1: sampling``.

    Parameters
    ----------
    say : callable
        Called with each line (default ``print``, flushed).

    Examples
    --------
    >>> display = LineDisplay()
    >>> display.queued(["M0", "M1"])
    queued: M0, M1
    >>> display.running("M1"); display.note("M1", "850 draws/s"); display.done("M1", 2.0)
    [2/2] M1: running
    [2/2] M1: done in 2.0 s (850 draws/s)
    """

    def __init__(self, say: Callable[[str], None] | None = None) -> None:
        self._say = say or (lambda text: print(text, flush=True))
        self._states = _States()
        self._lock = threading.Lock()

    def queued(self, keys: Sequence[str]) -> None:
        """Print the queue once."""
        with self._lock:
            self._states.add(keys)
            if keys:
                self._say("queued: " + ", ".join(keys))

    def _line(self, key: str, text: str) -> None:
        with self._lock:
            self._say(f"{self._states.position(key)} {key}: {text}")

    def running(self, key: str) -> None:
        """Print that ``key`` started."""
        self._line(key, "running")

    def phase(self, key: str, text: str) -> None:
        """Print the phase."""
        self._line(key, text)

    def note(self, key: str, text: str) -> None:
        """Keep the note for the done line."""
        with self._lock:
            self._states.notes[key] = text

    def done(self, key: str, seconds: float) -> None:
        """Print the wall time and the note."""
        self._line(key, self._states.finished_text(key, seconds))

    def failed(self, key: str, error: str) -> None:
        """Print the error."""
        self._line(key, f"FAILED: {error}")

    def write(self, text: str) -> None:
        """Print ``text``."""
        with self._lock:
            self._say(text)


class BarDisplay(TaskDisplay):
    """One live line per task on a terminal (``tqdm``), with the elapsed time ticking.

    Parameters
    ----------
    stream : file, optional
        Default ``sys.stdout``.
    refresh_s : float
        Seconds between redraws of the running tasks' clocks.

    Examples
    --------
    >>> import io
    >>> display = BarDisplay(io.StringIO())
    >>> display.queued(["M0"]); display.running("M0"); display.done("M0", 0.5)
    >>> display.close()
    """

    def __init__(self, stream: IO[str] | None = None, *, refresh_s: float = 1.0) -> None:
        self._stream = stream or sys.stdout
        self._states = _States()
        self._bars: dict[str, Any] = {}
        self._lock = threading.RLock()
        self._closed = threading.Event()
        self._ticker = threading.Thread(target=self._tick, args=(refresh_s,), daemon=True)
        self._ticker.start()

    def _bar(self, key: str):
        from tqdm import tqdm

        if key not in self._bars:
            self._states.add([key])
            size = shutil.get_terminal_size()  # 80 x 24 when the terminal does not say
            self._bars[key] = tqdm(
                total=0, position=len(self._bars), bar_format="{desc}", file=self._stream,
                leave=True, ncols=size.columns, nrows=size.lines,
            )  # fmt: skip
        return self._bars[key]

    def _show(self, key: str) -> None:
        phase = self._states.phase[key]
        since = self._states.since.get(key)
        clock = f"  {time.perf_counter() - since:5.0f} s" if since and phase_is_live(phase) else ""
        self._bar(key).set_description_str(f"{key:<10} {phase}{clock}", refresh=True)

    def _set(self, key: str, phase: str) -> None:
        with self._lock:
            self._bar(key)
            self._states.phase[key] = phase
            self._show(key)

    def _tick(self, refresh_s: float) -> None:
        while not self._closed.wait(refresh_s):
            with self._lock:
                for key, phase in self._states.phase.items():
                    if phase_is_live(phase):
                        self._show(key)

    def queued(self, keys: Sequence[str]) -> None:
        """A line per task."""
        for key in keys:
            self._set(key, "queued")

    def running(self, key: str) -> None:
        """Start the task's clock."""
        with self._lock:
            self._states.since[key] = time.perf_counter()
            self._set(key, "running")

    def phase(self, key: str, text: str) -> None:
        """Show the phase."""
        self._set(key, text)

    def note(self, key: str, text: str) -> None:
        """Keep the note for the done line."""
        with self._lock:
            self._states.notes[key] = text

    def done(self, key: str, seconds: float) -> None:
        """Show the wall time and the note."""
        self._set(key, self._states.finished_text(key, seconds))

    def failed(self, key: str, error: str) -> None:
        """Show the error (first line, shortened)."""
        first = (error.splitlines() or [""])[0]
        self._set(key, "FAILED: " + (first if len(first) <= 90 else first[:87] + "..."))

    def write(self, text: str) -> None:
        """Print above the task lines."""
        from tqdm import tqdm

        with self._lock:
            tqdm.write(text, file=self._stream)

    def close(self) -> None:
        """Stop the clock and leave the lines on the screen."""
        self._closed.set()
        with self._lock:
            for bar in self._bars.values():
                bar.close()
            self._bars.clear()


def phase_is_live(phase: str) -> bool:
    """Whether a task in this phase is running (its clock ticks).

    Examples
    --------
    >>> phase_is_live("sampling"), phase_is_live("queued"), phase_is_live("done in 2 s")
    (True, False, False)
    """
    return not (phase == "queued" or phase.startswith(("done", "FAILED")))


def task_display(stream: IO[str] | None = None, *, quiet: bool = False) -> TaskDisplay:
    """The display for ``stream``: live lines on a terminal, plain lines otherwise.

    Parameters
    ----------
    stream : file, optional
        Default ``sys.stdout``.
    quiet : bool
        Show nothing.

    Examples
    --------
    >>> import io
    >>> type(task_display(io.StringIO())).__name__
    'LineDisplay'
    >>> type(task_display(quiet=True)).__name__
    'TaskDisplay'
    """
    stream = stream or sys.stdout
    if quiet:
        return TaskDisplay()
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return BarDisplay(stream)
    return LineDisplay(lambda text: print(text, file=stream, flush=True))
