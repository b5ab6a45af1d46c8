"""Pieces of the run loop shared by :func:`sim.run.run_scene` and :func:`sim.dem.run_dem`.

* :func:`prepare_out_dir`: a new run never merges into an old one; the files
  of a run already in the folder are moved aside into ``previous/`` (one generation).
* :class:`InterruptGuard`: SIGINT and SIGTERM only set a flag while a run is
  inside compiled kernels (no exception can surface inside numba's dispatcher,
  which gave ``SystemError: ... returned a result with an exception set``);
  the loop calls :meth:`InterruptGuard.check` between kernel calls, which
  raises :class:`KeyboardInterrupt` (the CLI exits 130). Kernels are called in
  pieces of bounded wall time (:class:`WallClockChunker`), so a signal stops a
  run within about a second.
* :class:`SegmentedTable`: the streamed trajectories table written as
  segments that are committed together with a checkpoint. A segment is a
  complete Parquet file (closed, renamed into place) before the checkpoint
  that lists it is written, so after a kill (even SIGKILL, even twice) a
  resume keeps exactly the frames the checkpoint has, and the final table
  equals the uninterrupted run's. :meth:`SegmentedTable.finish` assembles the
  segments into ``trajectories.parquet``.
"""
from __future__ import annotations

import json
import logging
import shutil
import signal
import threading
import time
from pathlib import Path

log = logging.getLogger("sim.driver")

RUN_FILES = ("trajectories.parquet", "trajectories.parquet.part", "scene.json", "checkpoint.npz",
             "last_good_state.npz", "dem_summary.json", ".segments")
SEGMENT_DIR = ".segments"


def holds_run(out_dir) -> bool:
    """True when ``out_dir`` contains files of a simulation run."""
    out_dir = Path(out_dir)
    return out_dir.is_dir() and any((out_dir / f).exists() for f in RUN_FILES)


def prepare_out_dir(out_dir) -> bool:
    """Create ``out_dir`` for a new run, moving the files of an earlier run into ``out_dir/previous/``
    (replacing what an older run left there).

    Returns True when the folder was created here (so a refused run can
    remove it again with :func:`discard_if_empty`).
    """
    out_dir = Path(out_dir)
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    if holds_run(out_dir):
        # one generation is kept: repeated runs into one folder (make run, studies) must not pile up
        # copies of large tables; the run before the previous one is deleted
        dest = out_dir / "previous"
        if dest.exists():
            shutil.rmtree(dest)
        dest.mkdir()
        for f in RUN_FILES:
            if (out_dir / f).exists():
                (out_dir / f).rename(dest / f)
        log.warning("%s held a run; its files were moved to %s", out_dir, dest)
    return created


def discard_if_empty(out_dir, created: bool) -> None:
    """Remove ``out_dir`` if this run created it and left nothing in it."""
    out_dir = Path(out_dir)
    if created and out_dir.is_dir() and not any(out_dir.iterdir()):
        out_dir.rmdir()


class InterruptGuard:
    """Context manager: SIGINT/SIGTERM set a flag; :meth:`check` raises KeyboardInterrupt.

    Only installed in the main thread (signal handlers cannot be set
    elsewhere; dask workers run cases without it).
    """

    def __init__(self):
        self.signum = None
        self._old = {}

    def _handler(self, signum, frame):
        self.signum = signum

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self._old[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc):
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old = {}
        return False

    @property
    def stopped(self) -> bool:
        return self.signum is not None

    def check(self):
        """Raise KeyboardInterrupt if a signal arrived."""
        if self.signum is not None:
            raise KeyboardInterrupt(f"signal {signal.Signals(self.signum).name}")


class WallClockChunker:
    """Sizes of kernel calls so that each takes about ``seconds`` of wall time.

    Starts at ``first`` units (steps, or particles) and rescales from the
    measured time of each call (between 1/4 and 4 times the last size).
    """

    def __init__(self, first: int, seconds: float = 0.25, limit: int | None = None):
        self.size = max(1, int(first))
        self.seconds = seconds
        self.limit = limit
        self._t = None

    def start(self):
        self._t = time.perf_counter()

    def done(self, units: int):
        el = time.perf_counter() - self._t
        if units > 0:
            per = el / units
            want = self.seconds / per if per > 0 else 4 * self.size
            self.size = int(max(1, min(4 * self.size, max(self.size // 4, want))))
            if self.limit:
                self.size = min(self.size, self.limit)


class SegmentedTable:
    """Trajectory frames written as Parquet segments committed together with checkpoints.

    Parameters
    ----------
    out_dir : Path
        The run folder; segments live in ``out_dir/.segments``.
    meta : dict
        Table metadata (as for :class:`ptrack.table.TrajectoryWriter`); the
        key ``run`` (the scene fingerprint) ties each segment to its run.
    committed : list of str, optional
        Segment names committed by the checkpoint a run resumes from; any
        other file in the segment folder is deleted (frames the checkpoint
        does not have).
    """

    def __init__(self, out_dir, meta: dict, committed=None):
        self.out_dir = Path(out_dir)
        self.dir = self.out_dir / SEGMENT_DIR
        self.meta = dict(meta)
        self.committed = list(committed or [])
        self._writer = None
        self._name = None
        self.dir.mkdir(parents=True, exist_ok=True)
        keep = set(self.committed)
        for f in self.dir.iterdir():
            if f.name not in keep:
                f.unlink()

    def check_committed(self, run_key: str, through_frame: int) -> None:
        """Refuse (UserError) unless the committed segments exist, belong to ``run_key`` and end at
        ``through_frame``."""
        import pyarrow.parquet as pq

        from ptrack.errors import UserError
        from ptrack.table import META_KEY

        last = -1
        for name in self.committed:
            path = self.dir / name
            if not path.is_file():
                raise UserError(f"the checkpoint lists table segment {path}, which is missing",
                                "rerun without --resume (the table and the checkpoint do not belong together)")
            md = pq.read_schema(str(path)).metadata or {}
            meta = json.loads(md.get(META_KEY.encode(), b"{}"))
            if meta.get("run") != run_key:
                raise UserError(f"table segment {path} belongs to another run (scene or seed differ)",
                                "resume with the scene and seed of that run, or rerun without --resume")
            last = max(last, int(pq.read_table(str(path), columns=["frame"])["frame"].to_numpy().max()))
        if last != through_frame:
            raise UserError(f"the committed table ends at frame {last}, the checkpoint at frame {through_frame}",
                            "rerun without --resume (the table and the checkpoint do not belong together)")

    def open(self, first_frame: int):
        """Start a segment whose first frame is ``first_frame``."""
        from ptrack.table import TrajectoryWriter

        self._name = f"seg-{first_frame:07d}.parquet"
        self._writer = TrajectoryWriter(self.dir / self._name, self.meta)

    def append(self, df):
        if self._writer is None:
            raise RuntimeError("SegmentedTable.append before open")
        self._writer.append(df)

    def commit(self) -> list:
        """Close the open segment (a complete file from now on); returns the committed names,
        to be stored in the checkpoint written next."""
        if self._writer is not None:
            self._writer.close()
            if (self.dir / self._name).exists():
                self.committed.append(self._name)
            self._writer = None
        return list(self.committed)

    def finish(self, path, meta: dict, failed: str | None = None) -> Path:
        """Write ``path`` from every segment (committed and open), in frame order.

        ``failed``: the table is marked incomplete with this reason, the open
        (uncommitted) segment is deleted and the committed ones kept for a
        resume; otherwise the segment folder is removed.
        """
        from ptrack.table import TrajectoryWriter

        import pyarrow.parquet as pq

        names = list(self.committed)
        if self._writer is not None:
            self._writer.close()
            self._writer = None
            if (self.dir / self._name).exists():
                names.append(self._name)
        out = TrajectoryWriter(path, meta)
        for name in names:
            pf = pq.ParquetFile(str(self.dir / name))
            for g in range(pf.num_row_groups):
                out.append(pf.read_row_group(g).to_pandas())
        out.close(failed=failed)
        if failed:
            for name in names:
                if name not in self.committed:
                    (self.dir / name).unlink(missing_ok=True)
        else:
            shutil.rmtree(self.dir, ignore_errors=True)
        return Path(path)


# --------------------------------------------------------------------------- the frame loop
class Periodic:
    """Trigger: every ``every`` output frames (0 = never). Deterministic, as the DEM engine needs
    (it rebuilds its neighbour list at checkpoint frames so a resume is bit-identical)."""

    def __init__(self, every: int):
        self.every = int(every)

    def __call__(self, frame: int) -> bool:
        return self.every > 0 and frame % self.every == 0

    def ahead(self, frame: int) -> bool:
        """Whether the trigger fires at ``frame`` (known before the frame is computed)."""
        return self(frame)


class WallClock:
    """Trigger: at the first frame at least ``seconds`` of wall time after the last firing (for
    runs whose state does not depend on where checkpoints fall, e.g. free particles)."""

    def __init__(self, seconds: float):
        self.seconds = float(seconds)
        self._last = time.monotonic()

    def __call__(self, frame: int) -> bool:
        now = time.monotonic()
        if now - self._last >= self.seconds:
            self._last = now
            return True
        return False


class RunFailure(Exception):
    """Raised by an ``advance`` callback of :func:`run_frames`: the run cannot go on.

    ``frames``: a table chunk of the frames that are still good (or None);
    ``reason``: recorded in the table as why it is incomplete; ``error``: the
    :class:`ptrack.errors.UserError` to raise once the table is written.
    """

    def __init__(self, reason: str, error: Exception, frames=None):
        super().__init__(reason)
        self.reason = reason
        self.error = error
        self.frames = frames


def run_frames(*, table: SegmentedTable, traj_path, meta: dict, frame: int, n_out: int, advance, first=None,
               checkpoint=None, trigger=None, guard: InterruptGuard, bar=None, group: int = 1) -> int:
    """The one frame loop of every run (free particles and DEM).

    Parameters
    ----------
    table, traj_path, meta
        The segmented table and where :meth:`SegmentedTable.finish` writes it.
    frame, n_out
        The last frame already in the table (0 for a new run, whose frame 0 is
        ``first``) and the last frame of the run.
    advance : callable
        ``advance(frame, k) -> (df, k_done)``: compute up to ``k`` frames after
        ``frame`` and return their table chunk; raises :class:`RunFailure`.
    checkpoint : callable, optional
        ``checkpoint(frame, segment_names)``: save the state after ``frame``
        (called after the table segment is committed, so the two belong
        together), when ``trigger(frame)`` fires.
    guard : InterruptGuard
        Checked after every chunk (the callbacks poll it inside long chunks).
    group : int
        Frames per ``advance`` call.

    Returns
    -------
    int : the last frame written.

    Raises
    ------
    UserError
        From a :class:`RunFailure` (after the table is written, marked incomplete).
    KeyboardInterrupt
        SIGINT/SIGTERM: the table holds the frames done, marked incomplete; the
        committed segments stay for a resume.
    """
    try:
        with guard:
            table.open(0 if first is not None else frame + 1)
            if first is not None:
                table.append(first)
            while frame < n_out:
                df, k = advance(frame, min(group, n_out - frame))
                table.append(df)
                frame += k
                if bar is not None:
                    bar.update(k)
                if checkpoint is not None and trigger is not None and trigger(frame):
                    checkpoint(frame, table.commit())
                    if frame < n_out:
                        table.open(frame + 1)
                guard.check()
    except RunFailure as f:
        if f.frames is not None and len(f.frames):
            table.append(f.frames)
        table.finish(traj_path, meta, failed=f.reason)
        raise f.error from None
    except BaseException as exc:
        why = f"interrupted ({exc})" if isinstance(exc, KeyboardInterrupt) else f"{type(exc).__name__}: {exc}"
        table.finish(traj_path, meta, failed=why)
        raise
    finally:
        if bar is not None:
            bar.close()
    table.finish(traj_path, meta)
    return frame
