"""User-facing errors and safe file output.

A :class:`UserError` is a mistake the user can fix (missing file, bad
parameter, unstable time step). The CLI prints its message as one line
``error: <cause>; <fix>`` and exits with status 2. Output files are written
through :func:`atomic_output` so that a failure never leaves a half-written
file behind.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

EXIT_USER_ERROR = 2


class UserError(Exception):
    """A problem with the user's input: printed as one line, exit status 2.

    Parameters
    ----------
    cause : str
        What is wrong, naming the file, key or value.
    fix : str, optional
        What the user should do about it.
    """

    def __init__(self, cause: str, fix: str | None = None):
        self.cause = cause
        self.fix = fix
        super().__init__(cause if not fix else f"{cause}; {fix}")


def require_file(path, what: str = "file") -> Path:
    """Return ``path`` as a Path, or raise UserError if it is not a readable file."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"{what} not found: {p}", "check the path")
    if p.is_dir():
        raise UserError(f"{what} is a directory, not a file: {p}", "give a file path")
    if not os.access(p, os.R_OK):
        raise UserError(f"{what} is not readable: {p}", "check its permissions")
    return p


def check_positive(name: str, value, allow_zero: bool = False) -> float:
    """Validate a finite positive (or non-negative) scalar parameter.

    Raises UserError naming the parameter, the value and what is expected.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise UserError(f"{name} = {value!r} is not a number", f"give {name} as a number in SI units")
    import math

    if not math.isfinite(v):
        raise UserError(f"{name} = {value!r} is not finite", f"give a finite {name}")
    if v < 0 or (v == 0 and not allow_zero):
        expected = "non-negative" if allow_zero else "positive"
        raise UserError(f"{name} = {value!r} must be {expected}", f"give a {expected} {name}")
    return v


@contextlib.contextmanager
def atomic_output(path, mode: str = "wb"):
    """Open a temporary file beside ``path``; rename it onto ``path`` only on success.

    Yields the temporary *path* (str) when ``mode`` is None (for writers that
    take a file name, e.g. pandas/pyarrow/tifffile), else an open file object.
    On any exception the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    try:
        if mode is None:
            yield tmp
        else:
            with open(tmp, mode) as fh:
                yield fh
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
