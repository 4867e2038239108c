"""StageProgress: a bar on a terminal, plain lines with rate and time left in a log."""

import io

from rich.console import Console

from naka_gs_plugin.progress import StageProgress


def _run(terminal: bool, log_every: float) -> str:
    out = io.StringIO()
    console = Console(file=out, force_terminal=terminal, width=100)
    with StageProgress(console=console, log_every=log_every) as progress:
        task = progress.add_task("Enhancing", total=4)
        for _ in range(4):
            progress.advance(task)
    return out.getvalue()


def test_log_lines_off_a_terminal_first_and_last_item():
    lines = [line for line in _run(False, log_every=1e9).splitlines() if line.startswith("Enhancing:")]
    assert len(lines) == 2  # the first item and the last; the interval is never reached
    assert lines[0].startswith("Enhancing: 1/4 in ") and "/s, " in lines[0] and lines[0].endswith(" s left)")
    assert lines[1].startswith("Enhancing: 4/4 in ")


def test_every_item_logged_when_the_interval_is_zero():
    lines = [line for line in _run(False, log_every=0.0).splitlines() if line.startswith("Enhancing:")]
    assert [line.split(" in ")[0] for line in lines] == [f"Enhancing: {i}/4" for i in range(1, 5)]


def test_no_plain_lines_on_a_terminal():
    assert "Enhancing:" not in _run(True, log_every=0.0)
