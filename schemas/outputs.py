"""Outputs of the four commands: checked before any work starts, written whole or not at all.

    out = outputs.check_file(args.out, "--out", suffixes=(".json",))   # before the computing
    ...
    outputs.write_json(out, result)                                     # a temporary, a rename

`check_dir` / `check_file` refuse, in one line (UserError), an output that is of the wrong kind
(a file where a directory is wanted, a directory where a file is, a wrong suffix) or that cannot
be written (proved by creating and removing a probe file in the nearest existing folder); they
create nothing, so a command refused later leaves nothing behind. `atomic` writes a file under
a hidden temporary name beside it (`partial_path`) and renames it onto its name when complete,
so a crash, Ctrl-C or a full disk never leaves a file a reader takes as whole.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from schemas.errors import UserError


def partial_path(path: Path) -> Path:
    """Where a file for `path` is written until complete: hidden `.NAME.partial.EXT` beside it
    (the suffix kept, so writers that choose their format by it still do)."""
    path = Path(path)
    return path.with_name(f".{path.stem}.partial{path.suffix}")


def _label(path: Path, flag: str | None) -> str:
    return f"{flag} {path}" if flag else str(path)


def _probe(folder: Path, path: Path, flag: str | None) -> None:
    """UserError unless a file can be created in `folder` or, if it does not exist yet, in its
    nearest existing ancestor (which must be a directory)."""
    existing = next(p for p in (folder, *folder.parents) if p.exists() or p == p.parent)
    if not existing.is_dir():
        raise UserError(f"{_label(path, flag)}: {existing} is not a directory")
    try:
        fd, name = tempfile.mkstemp(dir=existing, prefix=".probe-")
        os.close(fd)
        os.unlink(name)
    except OSError as e:
        # /proc and the like answer "No such file or directory" for the folder they list
        why = f" ({e.strerror})" if e.strerror and e.errno != errno.ENOENT else ""
        raise UserError(f"{_label(path, flag)}: cannot write in {existing}{why}") from None


def check_dir(path: str | Path, flag: str | None = "--out") -> Path:
    """`path` as a directory the command may create or write into; UserError in one line if it
    is a file or cannot be written. Creates nothing."""
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        raise UserError(f"{_label(path, flag)}: not a directory")
    _probe(path, path, flag)
    return path


def check_file(
    path: str | Path, flag: str | None = "--out", suffixes: tuple[str, ...] = ()
) -> Path:
    """`path` as a file the command may write (replacing it if it exists); UserError in one
    line if it is a directory, lacks one of `suffixes` (lower case, with the dot) or cannot be
    written. Creates nothing."""
    path = Path(path).expanduser()
    if path.is_dir():
        raise UserError(f"{_label(path, flag)}: is a directory, expected a file")
    if suffixes and path.suffix.lower() not in suffixes:
        raise UserError(f"{_label(path, flag)}: must end in {' or '.join(suffixes)}")
    _probe(path.parent, path, flag)
    return path


@contextlib.contextmanager
def atomic(path: str | Path) -> Iterator[Path]:
    """Yields the temporary path to write `path`'s content to; renames it onto `path` when the
    block ends normally (folders created), removes it on any exception (Ctrl-C included). An
    OSError (a full disk, a folder that cannot be written) becomes a UserError naming `path`."""
    path = Path(path)
    tmp = partial_path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise UserError(f"cannot write {path} ({e.strerror or e})") from None
        raise


def write_text(path: str | Path, text: str) -> Path:
    """Write `text` to `path` atomically."""
    with atomic(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_json(path: str | Path, doc: object, indent: int | None = 1, **kwargs) -> Path:
    """Write `doc` as JSON (and a final newline) to `path` atomically."""
    return write_text(path, json.dumps(doc, indent=indent, **kwargs) + "\n")
