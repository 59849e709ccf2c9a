"""Progress of long loops as a user sees it: a live bar on a terminal, plain periodic lines elsewhere.

`progress_bar(total, desc)` draws a tqdm bar when its stream is a terminal; in a log file or a
pipe a bar's carriage returns would pile up into one unreadable line, so there it prints a plain
line now and then ("DESC: 300/1000 (30%) loss=0.12") and one at the end. `say(message)` prints
a line of output that does not break a bar drawn meanwhile.

Ground floor: nothing from gvae_core; tqdm is imported only when a bar is drawn.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["progress_bar", "say", "LINE_EVERY_SECONDS", "LINE_EVERY_FRACTION"]

#: A plain progress line comes when both this many seconds and this share of the total have
#: passed since the last one (and once at the end): a few lines per job, never one per step.
LINE_EVERY_SECONDS = 10.0
LINE_EVERY_FRACTION = 0.1


def _format_value(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


class _Off:
    """A bar that shows nothing (`enabled=False`)."""

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, **values) -> None:
        pass

    def write(self, message: str) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Lines(_Off):
    """Plain lines for a stream that is not a terminal: "DESC: n/total (pct%) k=v, ..." when
    `every_seconds` and `every_fraction` of the total have both passed since the last line, and
    at `close`. No carriage return is ever written."""

    def __init__(self, total: int, desc: str, stream: TextIO, every_seconds: float, every_fraction: float):
        self.total, self.desc, self.stream = max(int(total), 0), desc, stream
        self.every_seconds, self.every_fraction = float(every_seconds), float(every_fraction)
        self.n, self.postfix = 0, {}
        self.started = self._last_time = time.monotonic()
        self._last_n = 0
        self._closed = False

    def update(self, n: int = 1) -> None:
        self.n += int(n)
        now = time.monotonic()
        step = self.every_fraction * self.total if self.total else 1
        if now - self._last_time >= self.every_seconds and self.n - self._last_n >= step:
            self._line(now)

    def set_postfix(self, **values) -> None:
        self.postfix = {k: _format_value(v) for k, v in values.items()}

    def write(self, message: str) -> None:
        print(message, flush=True)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if self.n != self._last_n or self.n == 0:
                self._line(time.monotonic())

    def _line(self, now: float) -> None:
        count = f"{self.n}/{self.total} ({100 * self.n // self.total}%)" if self.total else f"{self.n}"
        values = ", ".join(f"{k}={v}" for k, v in self.postfix.items())
        print(f"{self.desc}: {count}" + (f" {values}" if values else "") + f" [{now - self.started:.0f} s]",
              file=self.stream, flush=True)
        self._last_time, self._last_n = now, self.n


class _Bar(_Off):
    """A tqdm bar on a terminal (kept on screen when done, as wide as the terminal)."""

    def __init__(self, total: int, desc: str, stream: TextIO, unit: str):
        from tqdm import tqdm  # noqa: PLC0415 - only where a bar is drawn

        self._tqdm = tqdm
        self.bar = tqdm(total=total, desc=desc, file=stream, leave=True, dynamic_ncols=True, unit=unit)

    def update(self, n: int = 1) -> None:
        self.bar.update(n)

    def set_postfix(self, **values) -> None:
        self.bar.set_postfix({k: _format_value(v) for k, v in values.items()}, refresh=False)

    def write(self, message: str) -> None:
        self._tqdm.write(message, file=sys.stdout)

    def close(self) -> None:
        self.bar.close()


def progress_bar(total: int, desc: str, *, enabled: bool = True, stream: TextIO | None = None, unit: str = "it",
                 every_seconds: float = LINE_EVERY_SECONDS, every_fraction: float = LINE_EVERY_FRACTION):
    """A progress bar over `total` steps named `desc`: `.update(n=1)`, `.set_postfix(**values)`
    (shown with the next line drawn), `.write(message)` (a line of output that does not break the
    bar), `.close()`; also a context manager that closes it. On a terminal (`stream`, default
    sys.stderr, says isatty) a tqdm bar; elsewhere plain lines (`every_seconds`, `every_fraction`:
    how often; one at close); `enabled` False: nothing at all."""
    if not enabled:
        return _Off()
    stream = sys.stderr if stream is None else stream
    if _is_terminal(stream):
        return _Bar(total, desc, stream, unit)
    return _Lines(total, desc, stream, every_seconds, every_fraction)


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def say(message: str) -> None:
    """Print `message` as a line on stdout, above any tqdm bar open on a terminal (tqdm.write),
    else a plain print, flushed so that it shows in a log as it happens."""
    tqdm_module = sys.modules.get("tqdm")
    bars = getattr(getattr(tqdm_module, "tqdm", None), "_instances", None)
    if bars:
        tqdm_module.tqdm.write(message, file=sys.stdout)
    else:
        print(message, flush=True)
