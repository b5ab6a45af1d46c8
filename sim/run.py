"""The simulation loop: scene -> integrator -> trajectories streamed to Parquet.

:func:`run_scene` builds the particles of a scene, picks (or checks) the
integrator and time step, writes ``scene.json`` (the resolved scene, the
integrator, dt and why) and streams the trajectories table
(frame, t, particle, x, y, z, vx, vy, vz, radius; SI units) to
``trajectories.parquet`` one chunk of output frames at a time, so a long run
never holds all frames in memory.

Scenes with pair forces (contact, bonding, friction, near-field) are handed
to the DEM engine, ``sim.dem.run_dem``.

If positions or velocities become NaN/Inf, the run stops with a UserError
naming the time; the frames before it stay in ``trajectories.parquet``
(marked incomplete) and the last good state is written to
``last_good_state.npz``.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from ptrack.errors import UserError, atomic_output, missing_dirs, remove_empty_dirs
from sim.forces.drag import max_reynolds
from sim.integrate import (IntegratorChoice, _reynolds_at_balance, choose_integrator, ou_exact_kernel,
                           overdamped_kernel, trapezoidal_kernel, wall_tables)
from sim.driver import (SEGMENT_DIR, InterruptGuard, RunFailure, SegmentedTable, WallClock, WallClockChunker,
                        prepare_out_dir, run_frames)
from sim.scene import Scene
from sim.state import State, build_state, constant_force

log = logging.getLogger("sim.run")


@dataclasses.dataclass
class RunResult:
    """Where a run wrote its output and what it did."""
    trajectories: Path
    scene_json: Path
    choice: IntegratorChoice | None
    n_frames: int
    wall_time_s: float
    state: State | None = None
    already_complete: bool = False  # a --resume of a finished run: nothing was computed


def numba_seed(seed) -> int:
    """Integer seed for numba's generator derived from a scene seed (same seed -> same numbers)."""
    return int(np.random.default_rng(seed).integers(0, 2**31 - 1))


class Stepper:
    """Advance a :class:`State` frame by frame with the chosen free-particle integrator.

    Usable on its own (the studies use it without any file output)::

        st = build_state(scene); fc = constant_force(scene, st)
        choice = choose_integrator(scene, st, fc)
        stepper = Stepper(scene, st, fc, choice)
        pos, vel = stepper.advance(nframes)      # (nframes, N, 3) each
    """

    def __init__(self, scene: Scene, state: State, fconst: np.ndarray, choice: IntegratorChoice, seed=None):
        self.scene = scene
        self.state = state
        self.fconst = np.ascontiguousarray(fconst, dtype=np.float64)
        self.choice = choice
        self.vf = np.ascontiguousarray(scene.fluid.velocity, dtype=np.float64)
        self.B = np.ascontiguousarray(scene.fields.B, dtype=np.float64)
        self.box = np.ascontiguousarray(scene.domain.size, dtype=np.float64)
        self.modes = scene.boundaries.modes
        self.noise = scene.kT > 0.0
        self.kT = scene.kT
        self.failures = 0
        self.re_balance = float(np.max(_reynolds_at_balance(scene, state, self.fconst), initial=0.0))
        self.kernel_log: list[str] = []
        # key of the counter-based random numbers (sim.forces.brownian.counter_normal) and the steps done
        self.rng_seed = numba_seed(scene.seed if seed is None else seed)
        self.steps_done = 0

    def stokes_only(self) -> bool:
        """True if the drag stays in the Stokes branch (Re <= 1) now and at the force balance."""
        re_now = max_reynolds(self.state.vel, self.vf, self.state.radius, self.scene.fluid.density,
                              self.scene.fluid.viscosity)
        return re_now <= 1.0 and self.re_balance <= 1.0

    def advance(self, nframes: int, out_pos=None, out_vel=None, poll=None, chunker=None):
        """Advance ``nframes`` output intervals; return the frames (nframes, N, 3) of positions and velocities.

        With ``chunker`` (:class:`sim.driver.WallClockChunker`, in particle-steps) the particles are
        advanced in consecutive blocks of bounded wall time, with ``poll()`` between blocks; the
        kernels advance particles one after the other, so the random numbers, and the result, are
        those of one call.
        """
        st = self.state
        c = self.choice
        n = st.n
        if out_pos is None:
            out_pos = np.empty((nframes, n, 3))
            out_vel = np.empty((nframes, n, 3))
        if c.kind == "trapezoidal":
            spec = self.scene.integrator
            # the drag-law branching is skipped while Re stays <= 1; checked once per output interval
            for f in range(nframes):
                stokes = self.stokes_only()

                def call(i0, i1, f=f, stokes=stokes):
                    self.failures += trapezoidal_kernel(
                        st.pos, st.vel, st.radius, st.mass, st.gamma, st.charge, self.fconst, self.vf, self.B,
                        self.scene.fluid.density, self.scene.fluid.viscosity, self.kT, c.dt, c.steps_per_output, 1,
                        self.box, self.modes, out_pos[f:f + 1], out_vel[f:f + 1], self.noise, c.phi,
                        spec.tolerance, spec.max_iterations, stokes, i0, i1, self.rng_seed,
                        self.steps_done + f * c.steps_per_output)
                self._blocks(call, c.steps_per_output, poll, chunker)
        else:
            if c.kind == "ou_exact":
                def call(i0, i1):
                    ou_exact_kernel(st.pos, st.vel, st.radius, st.mass, st.gamma, self.fconst, self.vf, self.kT,
                                    c.dt, c.steps_per_output, nframes, self.box, self.modes, out_pos, out_vel,
                                    self.noise, i0, i1, self.rng_seed, self.steps_done)
            else:
                hindered = bool(self.scene.integrator.hindered_mobility)
                tabs = wall_tables() if hindered else (0.0, 1.0, np.zeros(2), np.zeros(2), np.zeros(2))

                def call(i0, i1):
                    overdamped_kernel(st.pos, st.vel, st.radius, st.gamma, self.fconst, self.vf, self.kT, c.dt,
                                      c.steps_per_output, nframes, self.box, self.modes, out_pos, out_vel,
                                      self.noise, hindered, *tabs, i0, i1, self.rng_seed, self.steps_done)
            self._blocks(call, nframes * c.steps_per_output, poll, chunker)
        st.t += nframes * self.scene.time.output_interval
        self.steps_done += nframes * c.steps_per_output
        return out_pos, out_vel

    def _blocks(self, call, steps, poll, chunker):
        """``call(i0, i1)`` over consecutive particle blocks of about ``chunker.size`` particle-steps."""
        n = self.state.n
        if chunker is None:
            call(0, n)
            return
        i0 = 0
        while i0 < n:
            i1 = min(n, i0 + max(1, chunker.size // max(steps, 1)))
            chunker.start()
            call(i0, i1)
            chunker.done((i1 - i0) * steps)
            i0 = i1
            if poll is not None and i0 < n:
                poll()


def _frame_table(frames: np.ndarray, t: np.ndarray, pos: np.ndarray, vel: np.ndarray, radius: np.ndarray) -> pd.DataFrame:
    nf, n = pos.shape[0], pos.shape[1]
    return pd.DataFrame({
        "frame": np.repeat(frames.astype(np.int64), n),
        "t": np.repeat(t, n),
        "particle": np.tile(np.arange(n, dtype=np.int64), nf),
        "x": pos[:, :, 0].ravel(), "y": pos[:, :, 1].ravel(), "z": pos[:, :, 2].ravel(),
        "vx": vel[:, :, 0].ravel(), "vy": vel[:, :, 1].ravel(), "vz": vel[:, :, 2].ravel(),
        "radius": np.tile(radius, nf),
    })


#: estimated run time (h, one core) above which a run is refused unless the caller allows more (``max_hours``)
MAX_RUN_HOURS = 4.0
#: particle-steps per second of each free-particle kernel on one core (measured, N = 2000, a loaded 2-core
#: machine; the trapezoidal rule iterates a fixed point at every step), for the estimate of the run time
PARTICLE_STEPS_PER_S = {"ou_exact": 2.0e6, "overdamped": 4.0e6, "trapezoidal": 1.5e6}


def check_cost(n: int, n_frames: int, choice: IntegratorChoice, max_hours: float = MAX_RUN_HOURS) -> float:
    """Refuse (UserError) a run whose estimated wall time exceeds ``max_hours``; returns the particle-steps.

    The cost is N x frames x steps per frame, with the dt and steps per
    output interval the run will use (``choice``, from
    :func:`sim.integrate.choose_integrator`: the kernels take exactly these),
    known before any step; the time is that cost at the measured rate of
    the chosen kernel (:data:`PARTICLE_STEPS_PER_S`). The message says why the
    steps are so many (dt and what chose it) and, when the Reynolds number is
    beyond Stokes flow or the tabulated drag law, that the physics is outside
    the model anyway.
    """
    from sim.electrokinetics import _CD_RE4

    cost = float(n) * n_frames * choice.steps_per_output
    hours = cost / PARTICLE_STEPS_PER_S.get(choice.kind, min(PARTICLE_STEPS_PER_S.values())) / 3600
    if hours <= max_hours:
        return cost
    why = (f"the run needs {cost:.2g} particle-steps ({choice.steps_per_output:.3g} steps of dt = {choice.dt:.3g} s "
           f"per output frame, {choice.kind}), about {hours:.3g} h on one core, over the {max_hours:g} h budget")
    if choice.re_estimate > _CD_RE4:
        why += (f"; the Reynolds number reaches {choice.re_estimate:.3g}, far outside the drag law "
                f"(tabulated to Re = {_CD_RE4:.3g}), so the result would not mean anything anyway")
    elif choice.re_estimate > 1.0:
        why += (f"; the Reynolds number reaches {choice.re_estimate:.3g}, far outside Stokes flow (Re <= 1) where "
                "the colloid physics of a scene (Brownian motion, Henry's charge) holds: the drive is unphysical "
                "for these particles")
    raise UserError(why, "lower the field or the charge, shorten time.final / output_interval, or allow more time "
                         "(simulate --max-hours)")


def run_complete(out_dir, fingerprint: str) -> int | None:
    """The number of frames of the finished run of ``fingerprint`` in ``out_dir``, or None.

    Finished: ``trajectories.parquet`` is there, written by this run (scene
    and seed: the table's ``run`` key), not marked incomplete, and no table
    segments wait for a resume.
    """
    import pyarrow.parquet as pq

    from ptrack.table import META_KEY

    out_dir = Path(out_dir)
    path = out_dir / "trajectories.parquet"
    if not path.is_file() or (out_dir / SEGMENT_DIR).exists():
        return None
    try:
        pf = pq.ParquetFile(str(path))
        # the footer's key-value metadata first (where "incomplete" is added at close), as read_table does
        raw = (pf.metadata.metadata or {}).get(META_KEY.encode()) or (pf.schema_arrow.metadata or {}).get(
            META_KEY.encode())
        meta = json.loads(raw or b"{}")
    except Exception:  # unreadable: not a finished run
        return None
    if meta.get("run") != fingerprint or meta.get("incomplete"):
        return None
    import pyarrow.compute as pc

    frames = pf.read(columns=["frame"])["frame"]
    return int(pc.count_distinct(frames).as_py())


def _tidy_failed(out_dir: Path, made: list) -> None:
    """After a failed or interrupted run: remove an empty segment folder (no committed frames to resume
    from) and the folders this run created, if nothing is left in them."""
    seg = out_dir / SEGMENT_DIR
    if seg.is_dir() and not any(seg.iterdir()):
        seg.rmdir()
    remove_empty_dirs(made)


def _write_state(path: Path, state: State, t: float) -> None:
    with atomic_output(path, "wb") as fh:
        np.savez(fh, t=t, pos=state.pos, vel=state.vel, radius=state.radius, mass=state.mass,
                 charge=state.charge)


def run_scene(scene: Scene, out_dir, seed=None, progress: bool = True, resume: bool = False,
              max_rows_per_chunk: int = 1_000_000, checkpoint_seconds: float = 30.0,
              max_hours: float = MAX_RUN_HOURS, threads: int | None = None) -> RunResult:
    """Run a scene and stream its trajectories to ``out_dir/trajectories.parquet``.

    Parameters
    ----------
    scene : Scene
    out_dir : path-like
        Output directory (created). Receives ``trajectories.parquet`` and
        ``scene.json`` (resolved scene, chosen integrator, dt and why).
    seed : int, optional
        Overrides ``scene.seed``.
    progress : bool
        tqdm progress bar on stderr.
    resume : bool
        Continue from ``out_dir/checkpoint.npz``: the table equals the
        uninterrupted run's, frame for frame. Refused at once (nothing
        written) without a checkpoint, or when the checkpoint, its table
        segments and the scene (with its seed) do not belong together. A run
        that already finished (:func:`run_complete`) is left as it is: the
        result has ``already_complete`` set and nothing is computed.
    max_rows_per_chunk : int
        Rows buffered before a chunk is appended to the Parquet file.
    checkpoint_seconds : float
        Free-particle runs: a checkpoint (with its committed table segment) at
        the first chunk of frames after this much wall time (DEM runs: every
        ``contact.checkpoint_every`` frames).
    max_hours : float
        Free particles: refuse a run estimated to take longer (h on one
        core, :func:`check_cost`).
    threads : int, optional
        DEM runs: threads of the pair kernel (:func:`sim.dem.dem_threads`:
        default ``PTRACK_THREADS``, else 1).

    Returns
    -------
    RunResult

    Raises
    ------
    UserError
        Unstable time step or an absurd estimated cost (:func:`check_cost`),
        both before anything is written; or NaN/Inf during the run (the
        frames so far and ``last_good_state.npz`` are kept).
    KeyboardInterrupt
        SIGINT or SIGTERM (checked between kernel calls of ~0.25 s): the
        frames completed so far are kept, marked incomplete.

    A folder that holds an earlier run gets that run's files moved into
    ``previous/`` (one generation) first (:func:`sim.driver.prepare_out_dir`).
    A run that fails or is interrupted before it has committed any frames
    leaves no empty segment folder, and no empty folder it created.
    """
    from sim.checkpoint import scene_fingerprint

    t0 = time.perf_counter()
    if seed is not None:
        scene = dataclasses.replace(scene, seed=int(seed))
    out_dir = Path(out_dir)
    fp = scene_fingerprint(scene.to_dict())  # covers the seed; the DEM engine computes the same key
    if resume:
        n_done = run_complete(out_dir, fp)
        if n_done is not None:
            log.info("run already complete: %s (%d frames)", out_dir / "trajectories.parquet", n_done)
            return RunResult(trajectories=out_dir / "trajectories.parquet", scene_json=out_dir / "scene.json",
                             choice=None, n_frames=n_done, wall_time_s=time.perf_counter() - t0,
                             already_complete=True)
    made = [] if resume else missing_dirs(out_dir)
    try:
        if scene.interactions is not None and getattr(scene.interactions, "any_pair_force", False):
            from sim.dem import run_dem
            return run_dem(scene, out_dir, resume=resume, progress=progress, threads=threads)
        return _run_free(scene, out_dir, fp, progress, resume, max_rows_per_chunk, checkpoint_seconds, max_hours)
    except BaseException:
        _tidy_failed(out_dir, made)
        raise


def _run_free(scene: Scene, out_dir: Path, fp: str, progress: bool, resume: bool, max_rows_per_chunk: int,
              checkpoint_seconds: float, max_hours: float) -> RunResult:
    """:func:`run_scene` for free particles (no pair forces)."""
    from sim.checkpoint import load_checkpoint, save_checkpoint

    traj_path = out_dir / "trajectories.parquet"
    ck_path = out_dir / "checkpoint.npz"
    scene_json = out_dir / "scene.json"
    if resume:
        # refused at once, before any work or any write
        ck_data, ck_head = load_checkpoint(ck_path, fp)
        if not (out_dir / SEGMENT_DIR).is_dir():
            raise UserError(f"{out_dir} has a checkpoint but no committed table segments (the run finished)",
                            "rerun without --resume")

    t0 = time.perf_counter()
    # everything that can refuse the run comes before anything is written
    state = build_state(scene)
    fconst = constant_force(scene, state)
    choice = choose_integrator(scene, state, fconst)
    n_out = int(round(scene.time.final / scene.time.output_interval))
    check_cost(state.n, n_out, choice, max_hours)
    resolved = {"scene": scene.to_dict(), "integrator": choice.to_dict(), "n_output_frames": n_out + 1,
                "gravity_note": "gravity with buoyancy is on unless [gravity] enabled = false",
                "units": "SI"}
    meta = {"source": "sim", "frame_interval": scene.time.output_interval, "scene": scene.source,
            "integrator": choice.kind, "dt": choice.dt, "integrator_reason": choice.reason, "seed": scene.seed,
            "run": fp}
    stepper = Stepper(scene, state, fconst, choice)
    frame = 0
    if resume:
        table = SegmentedTable(out_dir, meta, committed=ck_head.get("segments", []))
        frame = int(ck_head["frame"])
        table.check_committed(fp, frame)
        state.pos = np.ascontiguousarray(ck_data["pos"])
        state.vel = np.ascontiguousarray(ck_data["vel"])
        state.t = float(ck_data["t"])
        stepper.steps_done = int(ck_data["steps_done"])
        stepper.failures = int(ck_data["failures"])
    else:
        prepare_out_dir(out_dir)  # the folders it makes are removed again by run_scene if the run fails empty
        table = SegmentedTable(out_dir, meta)
    with atomic_output(scene_json, "w") as fh:
        json.dump(resolved, fh, indent=2, default=float)
    n = state.n
    # frames per kernel call: bounded by the rows per Parquet chunk and by ~2e7 particle-steps (progress bar)
    group = max(1, min(n_out, max_rows_per_chunk // max(n, 1), int(2e7 // max(n * choice.steps_per_output, 1))))
    buf_pos = np.empty((group, n, 3))
    buf_vel = np.empty((group, n, 3))
    dt_out = scene.time.output_interval
    from tqdm import tqdm
    bar = tqdm(total=n_out, initial=frame, desc="simulate", unit="frame", disable=not progress, file=sys.stderr)
    guard = InterruptGuard()
    chunker = WallClockChunker(first=1_000_000)

    def advance(done, g):
        good = state.copy()
        stepper.advance(g, buf_pos[:g], buf_vel[:g], poll=guard.check, chunker=chunker)
        ok = np.isfinite(buf_pos[:g]).all(axis=(1, 2)) & np.isfinite(buf_vel[:g]).all(axis=(1, 2))
        if not ok.all():
            nbad = int(np.argmin(ok))
            part = None
            if nbad > 0:
                frames = np.arange(done + 1, done + 1 + nbad)
                part = _frame_table(frames, frames * dt_out, buf_pos[:nbad], buf_vel[:nbad], state.radius)
                good.pos = buf_pos[nbad - 1].copy()
                good.vel = buf_vel[nbad - 1].copy()
            t_good = (done + nbad) * dt_out
            _write_state(out_dir / "last_good_state.npz", good, t_good)
            t_bad = (done + nbad + 1) * dt_out
            reason = f"non-finite positions/velocities by t = {t_bad:.6g} s"
            raise RunFailure(reason, UserError(
                f"simulation stopped: {reason} (integrator {choice.kind}, dt = {choice.dt:.3g} s); "
                f"frames up to t = {t_good:.6g} s are in {traj_path}, last good state in "
                f"{out_dir / 'last_good_state.npz'}",
                "reduce time.dt or check the forces and parameters of the scene"), frames=part)
        frames = np.arange(done + 1, done + 1 + g)
        return _frame_table(frames, frames * dt_out, buf_pos[:g], buf_vel[:g], state.radius), g

    def checkpoint(done, names):
        # free particles: the state is positions, velocities, time and the step counter (the random
        # numbers are keyed by it), so checkpoints may fall anywhere without changing the run
        save_checkpoint(ck_path, {"pos": state.pos, "vel": state.vel, "t": np.float64(state.t),
                                  "steps_done": np.int64(stepper.steps_done), "failures": np.int64(stepper.failures)},
                        {"frame": done, "fingerprint": fp, "seed": scene.seed, "segments": names})

    first = None if resume else _frame_table(np.array([0]), np.array([0.0]), state.pos[None], state.vel[None],
                                             state.radius)
    run_frames(table=table, traj_path=traj_path, meta=meta, frame=frame, n_out=n_out, advance=advance,
               first=first, checkpoint=checkpoint, trigger=WallClock(checkpoint_seconds), guard=guard, bar=bar,
               group=group)
    if stepper.failures:
        log.warning("trapezoidal fixed-point iteration did not converge in %d steps", stepper.failures)
    resolved["run"] = {"wall_time_s": time.perf_counter() - t0, "fixed_point_failures": stepper.failures,
                       "particle_steps": n * n_out * choice.steps_per_output}
    with atomic_output(scene_json, "w") as fh:
        json.dump(resolved, fh, indent=2, default=float)
    return RunResult(trajectories=traj_path, scene_json=scene_json, choice=choice, n_frames=n_out + 1,
                     wall_time_s=time.perf_counter() - t0, state=state)
