"""Output paths checked before a command does any work: an output is never a folder, never
one of the command's inputs (a result written over its own data), never another output."""
from __future__ import annotations

from pathlib import Path


def check_outputs(inputs: dict, outputs: dict, existing_folder: bool = False) -> None:
    """``inputs``: {description: path or None}; ``outputs``: {option: path or None}. Raises
    ValueError naming the option when an output is a folder, resolves to an input or to an
    earlier output, or (``existing_folder``) sits in a folder that does not exist."""
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
