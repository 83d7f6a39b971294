"""Output files written whole or not at all.

``atomic_file(path, mode="w", **open_kw)`` is a context manager yielding an open file
(``write_text_atomic(path, text)`` for a text built in memory): it
writes ``path`` + ".tmp" beside the target, flushes it to disk (fsync) and renames it over
the target only when the block ends without an error (``os.replace`` is atomic on POSIX).
On any error the temporary file is removed and the target is left as it was: a crash, a
full disk or a value the writer cannot serialise never leaves a half-written calibration,
marker file or skeleton where a reader would take it for a result, nor a stray ``*.tmp``.
Every writer of a result file uses it (capture's recording metadata and detections,
calibration files and reports, marker files, BVH and skeleton JSON).
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_file", "write_text_atomic"]


@contextmanager
def atomic_file(path, mode: str = "w", **open_kw):
    if mode not in ("w", "wb"):
        raise ValueError(f"mode={mode!r}, expected 'w' or 'wb'")
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, mode, **open_kw) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path, text: str) -> Path:
    """``text`` written to ``path`` whole or not at all (``atomic_file``); returns the path."""
    path = Path(path)
    with atomic_file(path) as f:
        f.write(text)
    return path
