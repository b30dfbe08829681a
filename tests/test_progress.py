"""Progress displays: plain lines for logs, live lines on a terminal, nothing when quiet."""

from __future__ import annotations

import io

from kohpymc.progress import (
    BarDisplay,
    LineDisplay,
    TaskDisplay,
    report_note,
    report_phase,
    reporting_to,
    task_display,
)


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_display_follows_the_output():
    assert isinstance(task_display(_Terminal()), BarDisplay)
    assert type(task_display(io.StringIO())) is LineDisplay
    assert type(task_display(_Terminal(), quiet=True)) is TaskDisplay


def test_line_display_tells_each_event_with_the_task_position():
    lines = []
    display = LineDisplay(lines.append)
    display.queued(["M0", "M1"])
    display.running("M1")
    display.phase("M1", "sampling")
    display.note("M1", "900 draws/s")
    display.done("M1", 12.34)
    display.failed("M0", "RuntimeError: boom")
    assert lines == [
        "queued: M0, M1",
        "[2/2] M1: running",
        "[2/2] M1: sampling",
        "[2/2] M1: done in 12.3 s (900 draws/s)",
        "[1/2] M0: FAILED: RuntimeError: boom",
    ]


def test_bar_display_leaves_one_final_line_per_task():
    screen = _Terminal()
    display = BarDisplay(screen, refresh_s=0.01)
    display.queued(["M0", "M1"])
    display.running("M0")
    display.phase("M0", "sampling")
    display.done("M0", 2.0)
    display.failed("M1", "ValueError: " + "x" * 200)
    display.write("a line above")
    display.close()
    text = screen.getvalue()
    assert "M0         done in 2.0 s" in text
    assert "M1         FAILED: ValueError: xxx" in text and "x" * 100 not in text
    assert "a line above" in text


def test_reports_reach_the_reporter_of_the_running_task_only():
    seen = []
    report_phase("nobody listens")
    with reporting_to(lambda kind, text: seen.append((kind, text))):
        report_phase("compiling")
        report_note("10 draws/s")
    report_note("nobody listens")
    assert seen == [("phase", "compiling"), ("note", "10 draws/s")]
