"""Progress bars away from a terminal: plain lines every few percent, never carriage-return
frames (taskvar_torch/progress.py)."""

from __future__ import annotations

import io

from tqdm.std import tqdm

from taskvar_torch.progress import LineProgress, progress_bar


class Terminal(io.StringIO):
    """A stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


def test_a_stream_that_is_not_a_terminal_gets_a_bounded_number_of_plain_lines():
    log = io.StringIO()
    bar = progress_bar(total=10_000, desc="train", unit="frame", file=log)
    assert isinstance(bar, LineProgress)
    for i in range(10_000):
        bar.update(1)
        if i % 1000 == 0:
            bar.set_postfix({"loss": f"{1 / (i + 1):.3g}"})
    bar.close()
    bar.close()  # idempotent: no second last line
    text = log.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert len(lines) == 20  # one per 5%
    assert lines[0].startswith("train:   5% 500/10000 frame, ")
    assert lines[-1].startswith("train: 100% 10000/10000 frame, ") and "loss=" in lines[-1]


def test_lines_also_come_by_time_and_at_close():
    log = io.StringIO()
    bar = progress_bar(total=None, desc="sweep", unit="point", file=log, interval=0.0)
    for _ in range(3):
        bar.update(1)
    bar.close()
    assert log.getvalue().splitlines() == [
        line for line in log.getvalue().splitlines() if line.startswith("sweep: ")
    ]
    assert len(log.getvalue().splitlines()) == 3  # by time (interval 0); close adds nothing new

    log = io.StringIO()
    with progress_bar(total=1000, desc="eval", file=log, initial=100) as bar:  # a resumed run
        bar.update(20)  # under 5% more: no line yet
        assert log.getvalue() == ""
    assert log.getvalue().startswith("eval:  12% 120/1000 it, ")  # the last line, at close


def test_iterating_counts_items_and_prints_the_last_line():
    log = io.StringIO()
    items = list(progress_bar(range(7), desc="sweep", unit="point", file=log))
    assert items == list(range(7))
    lines = log.getvalue().splitlines()
    assert len(lines) <= 7 and lines[-1].startswith("sweep: 100% 7/7 point")


def test_a_terminal_gets_tqdm_and_disable_prints_nothing():
    assert isinstance(progress_bar(total=3, file=Terminal()), tqdm)
    log = io.StringIO()
    bar = progress_bar(total=3, file=log, disable=True)
    bar.update(3)
    bar.close()
    assert log.getvalue() == ""
