"""Progress for people: a bar on a terminal, periodic plain lines in a log file or a pipe."""

from __future__ import annotations



class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, **values) -> None:
        pass

    def close(self) -> None:
        pass

    def write(self, message: str) -> None:
        pass


def progress_bar(total: int, desc: str, *, enabled: bool = True, stream=None):
    """A progress bar (placeholder until the TTY-aware one lands)."""
    if not enabled:
        return _NoBar()
    from tqdm import tqdm  # noqa: PLC0415

    return tqdm(total=total, desc=desc, leave=True, dynamic_ncols=True, file=stream)


def say(message: str) -> None:
    """A line that does not break an open bar."""
    from tqdm import tqdm  # noqa: PLC0415

    tqdm.write(message)
