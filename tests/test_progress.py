"""Progress as a user sees it: a tqdm bar on a terminal, plain periodic lines in a log or a pipe,
nothing when disabled, and `say` that does not break a bar."""

from __future__ import annotations

import io
import subprocess
import sys

from gvae_core import progress
from gvae_core.progress import progress_bar, say


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_gets_a_plain_line_every_tenth_and_one_at_close():
    log = io.StringIO()
    with progress_bar(100, "train", stream=log, every_seconds=0.0) as bar:
        for step in range(1, 101):
            if step == 45:
                bar.set_postfix(loss=0.123456, views=4)
            bar.update()
    text = log.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert len(lines) == 10, lines  # at 10, 20, ..., 100: the close adds none after the last
    assert lines[0].startswith("train: 10/100 (10%)") and lines[-1].startswith("train: 100/100 (100%)")
    assert "loss=0.1235, views=4" in lines[4] and "loss" not in lines[3]


def test_plain_lines_wait_for_the_interval_and_the_close_always_says_where_it_ended():
    log = io.StringIO()
    bar = progress_bar(1000, "fit", stream=log, every_seconds=3600.0)
    bar.update(999)
    assert log.getvalue() == ""  # an hour has not passed
    bar.close()
    bar.close()  # (a second close adds nothing)
    (line,) = log.getvalue().splitlines()
    assert line.startswith("fit: 999/1000 (99%)")


def test_a_terminal_gets_a_tqdm_bar():
    screen = _Terminal()
    bar = progress_bar(10, "render", stream=screen)
    assert isinstance(bar, progress._Bar)
    for _ in range(10):
        bar.update()
    bar.set_postfix(psnr=30.5)
    bar.close()
    text = screen.getvalue()
    assert "\r" in text and "render" in text and "10/10" in text


def test_disabled_shows_nothing(capsys):
    log = io.StringIO()
    with progress_bar(5, "quiet", enabled=False, stream=log) as bar:
        bar.update(5)
        bar.set_postfix(a=1)
        bar.write("not shown")
    assert log.getvalue() == "" and capsys.readouterr().out == ""


def test_write_and_say_print_lines_without_a_bar(capsys):
    bar = progress_bar(3, "job", stream=io.StringIO())
    bar.write("a line")
    say("another")
    bar.close()
    assert capsys.readouterr().out == "a line\nanother\n"


def test_say_writes_above_an_open_terminal_bar():
    """With a bar open on a terminal `say` goes through tqdm.write, which clears the bar first."""
    code = ("import io, sys\n"
            "from gvae_core.progress import progress_bar, say\n"
            "class T(io.StringIO):\n"
            "    def isatty(self): return True\n"
            "screen = T()\n"
            "bar = progress_bar(4, 'job', stream=screen)\n"
            "bar.update()\n"
            "import tqdm\n"
            "calls = []\n"
            "tqdm.tqdm.write = classmethod(lambda cls, s, file=None, **k: calls.append(s))\n"
            "say('hello')\n"
            "bar.close()\n"
            "say('after')\n"
            "print(calls)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.splitlines() == ["after", "['hello']"]


def test_the_module_imports_no_tqdm_until_a_bar_is_drawn():
    code = ("import sys, io\n"
            "from gvae_core.progress import progress_bar, say\n"
            "progress_bar(3, 'x', stream=io.StringIO()).close(); say('s')\n"
            "print('tqdm' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.splitlines()[-1] == "False"
