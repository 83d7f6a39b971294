"""Output paths checked before a command does any work: an output is never a folder, never
one of the command's inputs (a result written over its own data), never another output, and
its folder (or the nearest existing folder above it, where the command creates the rest)
takes a file."""
from __future__ import annotations

import tempfile
from pathlib import Path


def check_outputs(inputs: dict, outputs: dict, existing_folder: bool = False) -> None:
    """``inputs``: {description: path or None}; ``outputs``: {option: path or None}. Raises
    ValueError naming the option when an output is a folder, resolves to an input or to an
    earlier output, (``existing_folder``) sits in a folder that does not exist, or cannot be
    written: the nearest existing folder on its path refuses a new file (permissions, a
    read-only file system; tested by creating and removing a temporary file there, since
    permission bits say nothing for root) or is a file."""
    taken = {name: Path(p).resolve() for name, p in inputs.items() if p is not None}
    for flag, path in outputs.items():
        if path is None:
            continue
        full = Path(path).resolve()
        if full.is_dir():
            raise ValueError(f"{flag} {path} is a folder, expected a file path")
        if existing_folder and not full.parent.is_dir():
            raise ValueError(f"{flag} {path}: folder {full.parent} does not exist")
        for name, other in taken.items():
            if full == other:
                raise ValueError(f"{flag} {path} is the same file as {name}")
        taken[flag] = full
        _check_writable(flag, path, full)


def _check_writable(flag: str, path, full: Path) -> None:
    folder = full.parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"{flag} {path}: {folder} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        raise ValueError(f"{flag} {path}: cannot write in {folder} ({e.strerror})") from None
