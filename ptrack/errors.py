"""User-facing errors and safe file output.

A :class:`UserError` is a mistake the user can fix (missing file, bad
parameter, unstable time step). The CLI prints its message as one line
``error: <cause>; <fix>`` and exits with status 2. It subclasses ValueError,
so ``except ValueError`` in a notebook catches it.

Output files are written through :func:`atomic_output` so that a failure never
leaves a half-written file behind; :func:`check_writable` checks an output
path before the work starts, :func:`output_dir` creates an output folder and
removes it again if the command fails before writing anything into it, and
:func:`os_error_message` turns an environment failure (full disk, permission
denied, read-only file system) into the same one-line ``cause; fix`` form.
"""
from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import shutil
from pathlib import Path

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports it


class UserError(ValueError):
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


def missing_dirs(path) -> list[Path]:
    """The folders ``mkdir -p path`` would create (``path`` and the missing parents), outermost first."""
    missing = []
    d = Path(path)
    while not d.exists() and d != d.parent:
        missing.append(d)
        d = d.parent
    return missing[::-1]


def _make_parents(directory: Path) -> list[Path]:
    """``mkdir -p directory``; return the folders it created, outermost first."""
    missing = missing_dirs(directory)
    Path(directory).mkdir(parents=True, exist_ok=True)
    return missing


def remove_empty_dirs(dirs) -> None:
    """Remove the folders ``dirs`` (outermost first, as :func:`missing_dirs` lists them) that are empty,
    innermost first; stop at the first that is not empty (one already gone is skipped)."""
    for d in reversed(list(dirs)):
        try:
            Path(d).rmdir()
        except FileNotFoundError:
            continue
        except OSError:  # not empty: leave it and its parents
            break



def _open_exclusive(directory: Path, name: str) -> tuple[int, str]:
    """Create a new temporary file with mode 0666 & ~umask (mkstemp would give 0600)."""
    for _ in range(100):
        tmp = str(directory / f".{name}.{secrets.token_hex(4)}.part")
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary file name", str(directory))


@contextlib.contextmanager
def atomic_output(path, mode: str = "wb"):
    """Open a temporary file beside ``path``; rename it onto ``path`` only on success.

    Yields the temporary *path* (str) when ``mode`` is None (for writers that
    take a file name, e.g. pandas/pyarrow/tifffile), else an open file object.
    On any exception (a full disk included) the temporary file is removed,
    ``path`` keeps its previous content, and folders created for it are
    removed again. The file gets the permissions of any new file (0666 less
    the umask), so colleagues on a shared disk can read it.
    """
    path = Path(path)
    created = _make_parents(path.parent)
    fd, tmp = _open_exclusive(path.parent, path.name)
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
        remove_empty_dirs(created)
        raise


def check_writable(path, what: str = "output", directory: bool = False, need_bytes: int | None = None) -> Path:
    """Check that ``path`` can be created or replaced, before any work; return it as a Path.

    Nothing is left behind: the check creates (and deletes) a probe file in the
    nearest existing folder on the way to ``path``.

    Parameters
    ----------
    path : path-like
        The output file (or folder, with ``directory=True``).
    what : str
        How to name it in the message, e.g. "--out".
    directory : bool
        ``path`` is a folder to write into (it may exist).
    need_bytes : int, optional
        Refuse if the file system has less free space than this.

    Raises
    ------
    UserError
        ``path`` is a folder where a file is expected (or the reverse), lies
        under a file, or its folder cannot be written (permissions, read-only
        file system, a pseudo file system such as /proc), or too little space.
    """
    p = Path(path)
    if p.exists():
        if directory and not p.is_dir():
            raise UserError(f"{what} {p} exists and is not a folder", "give a folder path")
        if not directory and p.is_dir():
            raise UserError(f"{what} {p} is a folder", "give a file path")
    base = p if directory else p.parent
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        raise UserError(f"{what} {p} lies under {base}, which is a file", "give a path in a folder")
    try:
        fd, probe = _open_exclusive(base, "ptrack-write-check")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UserError(f"{what} {p} cannot be written: {exc.strerror or exc} in {base}",
                        "choose a writable location (check permissions and that the disk is mounted read-write)")
    if need_bytes is not None:
        free = shutil.disk_usage(base).free
        if free < need_bytes:
            raise UserError(f"{what} {p} needs about {need_bytes / 1e6:.3g} MB, but only {free / 1e6:.3g} MB are free "
                            f"on {base}", "free some space or choose another location")
    return p


@contextlib.contextmanager
def output_dir(path, what: str = "--out", all_or_nothing: bool = False):
    """Create the output folder ``path`` for a command; remove it again if the command fails.

    ``path`` is checked first (:func:`check_writable`). Folders this call
    created are removed (innermost first) when the block raises and they are
    still empty, so a refused run, or one stopped by a full disk, leaves no
    empty folder. With ``all_or_nothing``, a folder this call created is
    removed with the files the block wrote into it (a movie without its
    ground truth is no use); in a folder that existed before, the files
    already written stay (each is complete: :func:`atomic_output`).
    Yields the folder as a Path.
    """
    p = check_writable(path, what, directory=True)
    created = _make_parents(p)
    try:
        yield p
    except BaseException:
        if all_or_nothing and created and created[-1] == p:
            shutil.rmtree(p, ignore_errors=True)
        remove_empty_dirs(created)
        raise


# errno -> what the user can do about it
_OS_FIXES = {
    errno.ENOSPC: "free some space or write to another disk",
    errno.EDQUOT: "free some space (disk quota exceeded) or write to another disk",
    errno.EFBIG: "write to a file system that allows larger files",
    errno.EACCES: "choose a location you may write to, or change its permissions",
    errno.EPERM: "choose a location you may write to, or change its permissions",
    errno.EROFS: "the file system is mounted read-only: choose another location",
    errno.ENOENT: "check the path",
    errno.ENOTDIR: "a part of the path is a file, not a folder: check the path",
    errno.EISDIR: "give a file path, not a folder",
    errno.ENAMETOOLONG: "use a shorter path",
    errno.EIO: "the disk reported an input/output error: check it, or use another one",
    errno.EMFILE: "too many open files: raise the limit (ulimit -n)",
}
_ERRNO_IN_TEXT = re.compile(r"\[errno (\d+)\]", re.IGNORECASE)


def os_error_message(exc: OSError) -> tuple[str, str] | None:
    """(cause, fix) for an OSError the user can act on (full disk, permissions...), else None.

    Also understands pyarrow's errors, which carry the errno in their text
    ("[errno 28] No space left on device") rather than in ``exc.errno``.
    """
    code = exc.errno
    if code not in _OS_FIXES:
        m = _ERRNO_IN_TEXT.search(str(exc))
        code = int(m.group(1)) if m else None
    if code not in _OS_FIXES:
        return None
    where = exc.filename
    if exc.filename2:
        where = f"{exc.filename} -> {exc.filename2}"
    cause = os.strerror(code) + (f": {where}" if where else "")
    return cause.replace("\n", " "), _OS_FIXES[code]
