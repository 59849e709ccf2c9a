"""The `gvae` command line: one subcommand per module in this package.

Each module listed in `COMMAND_MODULES` defines `register(subparsers)`, which adds its
subparser(s) (`COMMANDS` says which) and sets `func` (called with the parsed namespace; returns an
exit code). A module imports at its top only what `--help` needs; `run` imports the rest, so that
`gvae --help`, `info`, `convert` and `list-scenes` start without torch or Numba (a test checks).

`main` shows a warning as one line, `warning: MESSAGE` on stderr (not Python's file name, line
number and source line), and an error of the input or of memory as `gvae COMMAND: error: ...`.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import sys
import time
import warnings
from collections.abc import Iterator

from ..progress import say

COMMAND_MODULES = (
    "info",
    "convert",
    "render",
    "demo",
    "vae",
    "train",
    "scenes",
    "report",
    "compact",
    "sfm",
)
#: subcommand -> the module that registers it: `gvae COMMAND ...` imports that module alone.
COMMANDS = {"info": "info", "convert": "convert", "render": "render", "demo": "demo", "fit-vae": "vae",
            "refine": "vae", "train": "train", "make-scene": "scenes", "list-scenes": "scenes", "report": "report",
            "compact": "compact", "sfm": "sfm"}

#: --device help of the commands that train or render.
DEVICE_HELP = "torch device: cpu (default) or cuda[:N] (needs a CUDA build of torch and a GPU)"


def progress_lines():
    """A progress(fraction, message) callback for long jobs that prints a line when the stage (the
    message up to its first colon) changes, or every few seconds: not every step (`progress.say`:
    above a progress bar, flushed)."""
    last = [0.0, ""]

    def progress(fraction: float, message: str) -> None:
        now = time.perf_counter()
        if message.split(":")[0] != last[1] or now - last[0] > 5.0:
            say(f"  [{fraction:4.0%}] {message}")
            last[:] = [now, message.split(":")[0]]

    return progress


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every subcommand, or only of the module that registers `command`."""
    parser = argparse.ArgumentParser(prog="gvae", description="GaussianVAE: refine 3D Gaussian Splatting "
                                     "scenes past their training resolution.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in (COMMANDS[command],) if command in COMMANDS else COMMAND_MODULES:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return parser


def _format_warning(message, category, filename, lineno, line=None) -> str:
    """`warnings.formatwarning` of the command line: the message alone, on one line."""
    return "warning: " + " ".join(str(message).split()) + "\n"


@contextlib.contextmanager
def warnings_as_lines() -> Iterator[None]:
    """Within: every warning shown is one `warning: MESSAGE` line on stderr, without the file,
    line number and source line (which warnings show is left to the filters; one recorded, as
    by `warnings.catch_warnings(record=True)`, stays recorded); the previous
    `warnings.formatwarning` is put back after."""
    saved = warnings.formatwarning
    warnings.formatwarning = _format_warning
    try:
        yield
    finally:
        warnings.formatwarning = saved


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(next((a for a in argv if not a.startswith("-")), None))
    args = parser.parse_args(argv)
    with warnings_as_lines():
        try:
            return int(args.func(args) or 0)
        except (ValueError, FileNotFoundError) as exc:  # bad input: one clear line, no traceback
            print(f"gvae {args.command}: error: {exc}", file=sys.stderr)
            return 2
        except MemoryError as exc:  # an allocation refused midway: said, not a traceback
            print(f"gvae {args.command}: error: out of memory{f' ({exc})' if str(exc) else ''}; a smaller job "
                  "(image size, number of Gaussians or views) may fit", file=sys.stderr)
            return 1
