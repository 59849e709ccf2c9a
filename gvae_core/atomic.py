"""Atomic file writes: a failed or interrupted write leaves no file (or the old one) behind."""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import BinaryIO
from collections.abc import Callable


def atomic_write(path, write_body: Callable[[BinaryIO], object]) -> Path:
    """Call `write_body(file)` on a new temporary file beside `path`, then rename it into place.
    On any error the temporary file is removed and `path` is left as it was."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            write_body(f)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def atomic_write_text(path, text: str) -> Path:
    """Write `text` (UTF-8) to `path` atomically."""
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")))
