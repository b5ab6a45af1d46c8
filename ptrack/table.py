"""The trajectories table shared by experiment and simulation.

One row per particle per frame. Required columns: ``frame`` (int), ``t`` (s),
``particle`` (int), ``x``, ``y``, ``z`` (m; ``z`` is NaN for 2D data).
Optional columns (see :data:`OPTIONAL_COLUMNS`) carry image-space positions
(``x_px``, ``y_px``: ``x_px`` along columns, ``y_px`` along rows, centre of
pixel (0, 0) at (0, 0), as in trackpy), photometry, calibration correlation
``cm``, velocities (m/s) and ``radius`` (m).

Metadata (pixel size in m, frame interval in s, source, units, anything else
JSON-serialisable) lives in ``df.attrs["ptrack"]`` and travels with the file:
in the Parquet schema metadata, or in a leading ``# ptrack: {json}`` comment
line of a CSV file.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import UserError, atomic_output, require_file

REQUIRED_COLUMNS = ("frame", "t", "particle", "x", "y", "z")
OPTIONAL_COLUMNS = (
    "x_px", "y_px", "z_px", "mass", "size", "ecc", "signal", "cm", "chi2", "edge",
    "vx", "vy", "vz", "radius", "sigma_x", "sigma_y", "sigma_z",
)
UNITS = {
    "frame": "1", "t": "s", "particle": "1", "x": "m", "y": "m", "z": "m",
    "x_px": "px", "y_px": "px", "vx": "m/s", "vy": "m/s", "vz": "m/s",
    "radius": "m", "sigma_x": "m", "sigma_y": "m", "sigma_z": "m", "cm": "1", "chi2": "1",
}
META_KEY = "ptrack"


def metadata(df: pd.DataFrame) -> dict:
    """Return the table's metadata dict (created empty if absent)."""
    return df.attrs.setdefault(META_KEY, {})


def make_table(frame, t, particle, x, y, z=None, meta: dict | None = None, **optional) -> pd.DataFrame:
    """Build a validated trajectories table from arrays.

    Parameters
    ----------
    frame, particle : array_like of int
    t : array_like of float, s
    x, y : array_like of float, m
    z : array_like of float, m, optional
        Height; NaN (2D data) if omitted.
    meta : dict, optional
        Metadata, e.g. ``{"pixel_size": 1.03e-7, "frame_interval": 0.1}``.
    **optional
        Optional columns (names from :data:`OPTIONAL_COLUMNS` or others).
    """
    n = len(np.asarray(frame))
    cols = {
        "frame": np.asarray(frame, dtype=np.int64),
        "t": np.asarray(t, dtype=np.float64),
        "particle": np.asarray(particle, dtype=np.int64),
        "x": np.asarray(x, dtype=np.float64),
        "y": np.asarray(y, dtype=np.float64),
        "z": np.full(n, np.nan) if z is None else np.asarray(z, dtype=np.float64),
    }
    for k, v in optional.items():
        cols[k] = np.asarray(v)
    df = pd.DataFrame(cols)
    df.attrs[META_KEY] = dict(meta or {})
    return validate(df)


def validate(df: pd.DataFrame, source: str = "trajectories table") -> pd.DataFrame:
    """Check a trajectories table; return it with canonical dtypes, sorted by (particle, frame).

    Raises
    ------
    UserError
        Missing required columns, non-integer frames or particle ids, NaN or
        infinite x/y, duplicate (particle, frame) rows, negative frame numbers.
    """
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if "z" in missing and all(c in df.columns for c in ("frame", "t", "particle", "x", "y")):
        df = df.assign(z=np.nan)
        missing.remove("z")
    if "t" in missing and "frame" in df.columns:
        dt = metadata(df).get("frame_interval")
        if dt:
            df = df.assign(t=df["frame"].to_numpy() * float(dt))
            missing.remove("t")
    if missing:
        raise UserError(
            f"{source} lacks required column(s) {', '.join(missing)} (has: {', '.join(map(str, df.columns))})",
            "a trajectories table needs frame, t, particle, x, y, z in SI units (z may be NaN)",
        )
    for c in ("frame", "particle"):
        col = df[c]
        if not pd.api.types.is_integer_dtype(col):
            vals = pd.to_numeric(col, errors="coerce").to_numpy(dtype=float)
            if not np.all(np.isfinite(vals)) or np.any(vals != np.round(vals)):
                bad = col[~(np.isfinite(vals) & (vals == np.round(vals)))].iloc[0]
                raise UserError(f"{source}: column '{c}' has non-integer value {bad!r}",
                                f"'{c}' must hold whole numbers")
            df = df.assign(**{c: vals.astype(np.int64)})
        else:
            df = df.assign(**{c: col.astype(np.int64)})
    if (df["frame"] < 0).any():
        raise UserError(f"{source}: negative frame number {int(df['frame'].min())}", "frames count from 0")
    for c in ("t", "x", "y", "z"):
        if not pd.api.types.is_float_dtype(df[c]):
            try:
                df = df.assign(**{c: df[c].astype(np.float64)})
            except (TypeError, ValueError):
                raise UserError(f"{source}: column '{c}' is not numeric", f"'{c}' must hold numbers in SI units")
    for c in ("t", "x", "y"):
        bad = ~np.isfinite(df[c].to_numpy())
        if bad.any():
            i = int(np.argmax(bad))
            raise UserError(
                f"{source}: NaN or infinite '{c}' at particle {int(df['particle'].iloc[i])}, frame {int(df['frame'].iloc[i])}",
                "drop or fill these rows before analysis",
            )
    if np.isinf(df["z"].to_numpy()).any():
        raise UserError(f"{source}: infinite 'z' values", "use NaN for unknown heights")
    dup = df.duplicated(subset=["particle", "frame"])
    if dup.any():
        row = df[dup].iloc[0]
        raise UserError(
            f"{source}: duplicate rows for particle {int(row['particle'])} at frame {int(row['frame'])}",
            "each particle may appear once per frame",
        )
    attrs = dict(df.attrs)
    df = df.sort_values(["particle", "frame"], kind="stable").reset_index(drop=True)
    df.attrs.update(attrs)
    df.attrs.setdefault(META_KEY, {})
    return df


def to_jsonable(meta, finite: bool = False):
    """Convert numpy scalars/arrays, Paths, tuples (recursively) to JSON-ready Python objects.

    ``finite=True`` (reports, summaries): non-finite floats become None, so the
    output is valid JSON; table metadata keeps NaN (Parquet stores it).
    """
    def conv(v):
        if isinstance(v, (np.bool_,)):
            return bool(v)
        if isinstance(v, (np.floating, np.integer)):
            v = v.item()
        if finite and isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, np.ndarray):
            return conv(v.tolist())
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, dict):
            return {str(k): conv(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        return v
    return conv(meta)


def write_table(df: pd.DataFrame, path, fmt: str | None = None) -> Path:
    """Write a trajectories table to Parquet (default) or CSV, with its metadata.

    The format follows ``fmt`` or the file suffix (``.csv`` -> CSV). The file
    appears only when complete (written to a temporary file, then renamed).
    """
    path = Path(path)
    fmt = fmt or ("csv" if path.suffix.lower() == ".csv" else "parquet")
    meta = to_jsonable(dict(df.attrs.get(META_KEY, {})))
    meta.setdefault("units", {c: u for c, u in UNITS.items() if c in df.columns})
    if fmt == "csv":
        with atomic_output(path, "w") as fh:
            fh.write(f"# {META_KEY}: {json.dumps(meta)}\n")
            df.to_csv(fh, index=False)
    elif fmt == "parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pandas(df, preserve_index=False)
        md = dict(table.schema.metadata or {})
        md.pop(b"pandas", None)
        md[META_KEY.encode()] = json.dumps(meta).encode()
        table = table.replace_schema_metadata(md)
        with atomic_output(path, None) as tmp:
            pq.write_table(table, tmp)
    else:
        raise UserError(f"unknown table format {fmt!r}", "use 'parquet' or 'csv'")
    return path


def read_table(path, validate_table: bool = True) -> pd.DataFrame:
    """Read a trajectories table (Parquet or CSV) with its metadata in ``df.attrs['ptrack']``.

    Raises
    ------
    UserError
        Missing, unreadable or corrupt file, or a table that fails :func:`validate`.
    """
    path = require_file(path, "trajectories file")
    meta: dict = {}
    try:
        if path.suffix.lower() in (".csv", ".txt"):
            with open(path, encoding="utf-8") as fh:
                first = fh.readline()
            prefix = f"# {META_KEY}:"
            if first.startswith(prefix):
                meta = json.loads(first[len(prefix):])
            df = pd.read_csv(path, comment="#")
        else:
            import pyarrow.parquet as pq

            pf = pq.ParquetFile(path)
            table = pf.read()
            # the footer's key-value metadata: TrajectoryWriter adds "incomplete" there at close
            raw = (pf.metadata.metadata or {}).get(META_KEY.encode()) or (table.schema.metadata or {}).get(META_KEY.encode())
            if raw:
                meta = json.loads(raw)
            df = table.to_pandas()
    except UserError:
        raise
    except Exception as exc:  # corrupt / wrong format
        raise UserError(f"cannot read trajectories file {path}: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}".rstrip(": "),
                        "give a Parquet or CSV trajectories table (frame, t, particle, x, y, z in SI units)")
    df.attrs[META_KEY] = meta
    return validate(df, source=str(path)) if validate_table else df


class TrajectoryWriter:
    """Stream a trajectories table to Parquet in chunks (row groups).

    For long simulations and movies: the caller appends one chunk per output
    interval and never holds all frames in memory. The file is written as
    ``<path>.part`` and renamed to ``path`` by :meth:`close`.

    If the run fails for any other reason than the file itself (an error in
    the simulation, Ctrl-C), ``close(failed=reason)`` still finalises the
    frames written so far under ``path`` (so a long run loses no work), with
    the reason in the metadata (key ``"incomplete"``, written into the Parquet
    footer without reading the table back: memory stays bounded). If writing
    the file itself fails (full disk, I/O error), the footer cannot be
    written: the broken ``.part`` is removed, ``path`` keeps any previous
    content, and the OSError is raised again by :meth:`close` (the CLI turns
    it into one line). Never is a footer-less ``.part`` left behind.

    Parameters
    ----------
    path : path-like
        Destination ``.parquet`` file.
    meta : dict, optional
        Table metadata (pixel size, frame interval, source, scene...).
    """

    def __init__(self, path, meta: dict | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = self.path.with_name(self.path.name + ".part")
        self.meta = to_jsonable(dict(meta or {}))
        self._writer = None
        self._schema = None
        self._meta_written: dict | None = None
        self._broken: BaseException | None = None
        self.rows = 0

    def append(self, df: pd.DataFrame) -> None:
        """Append one chunk (a DataFrame with the table's columns)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        if self._broken is not None:
            raise self._broken
        table = pa.Table.from_pandas(df, preserve_index=False)
        if self._writer is None:
            md = dict(table.schema.metadata or {})
            md.pop(b"pandas", None)
            meta = dict(self.meta)
            meta.setdefault("units", {c: u for c, u in UNITS.items() if c in df.columns})
            self._meta_written = meta
            md[META_KEY.encode()] = json.dumps(meta).encode()
            self._schema = table.schema.with_metadata(md)
            self._writer = pq.ParquetWriter(str(self.tmp), self._schema)
        table = table.cast(self._schema)
        try:
            self._writer.write_table(table)
        except BaseException as exc:
            if isinstance(exc, OSError):  # the file itself failed: its footer can no longer be written
                self._broken = exc
            raise
        self.rows += len(df)

    def _discard(self) -> None:
        import contextlib

        with contextlib.suppress(Exception):
            self._writer.close()
        self._writer = None
        with contextlib.suppress(FileNotFoundError):
            self.tmp.unlink()

    def close(self, failed: str | None = None) -> Path:
        """Finalise the file. ``failed``: a reason recorded when the run stopped early.

        Raises
        ------
        OSError
            Writing the file failed (full disk, ...): nothing is left at
            ``<path>.part``, and ``path`` is as before the run.
        """
        if self._writer is None:
            if self._broken is not None:
                raise self._broken
            return self.path
        if self._broken is not None:
            self._discard()
            raise self._broken
        try:
            if failed:
                meta = dict(self._meta_written or {}, incomplete=failed)
                self._writer.add_key_value_metadata({META_KEY: json.dumps(meta)})
            self._writer.close()
        except OSError as exc:
            self._broken = exc
            self._discard()
            raise
        self._writer = None
        self.tmp.replace(self.path)
        return self.path

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        elif self._writer is not None or self._broken is not None:
            try:
                self.close(failed=f"{exc_type.__name__}: {exc}")
            except OSError:
                if self._broken is not exc:
                    raise
        return False
