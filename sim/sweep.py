"""Parameter sweeps: a grid of scene variants run as dask tasks, one summary table.

``ptrack sweep SCENE --set fields.E=[0,0,-1e4],[0,0,-2e4] --set particles.count=100,200 --replicates 3``
runs every combination of the given values (here 2 x 2 grid points, 3 replicates
each: 12 runs) through :func:`sim.run.run_scene`, one sub-folder per run, and
writes ``summary.csv`` and ``summary.parquet``: the swept scene values beside
the observables of each run.

Values
    ``KEY=V1,V2,...``: KEY is a dotted scene key (``section.key`` as in the
    TOML file, or ``seed``); the values are TOML values separated by commas
    (``1e-7,2e-7``, ``[0,0,-1e4],[0,0,-2e4]``, ``"overdamped","ou_exact"``;
    bare words are read as strings).  Every variant is validated by the scene
    validator (:func:`sim.scene.scene_from_dict`) before any run starts, so a
    bad key or value fails at once with one line.

Replicates
    Replicate 0 runs with the scene's own seed (so a one-replicate sweep
    reproduces ``ptrack simulate``); replicate r > 0 with
    ``SeedSequence([seed, r])`` (:func:`sim.studies._dask.case_seed`): distinct,
    deterministic, and the same for every grid point (common random numbers,
    which makes differences between grid points less noisy).

Resuming
    A run is complete when its folder holds ``case.json``, written atomically
    after the run with the run's scene (resolved), seed and observables.  A
    second sweep into the same folder skips a run whose ``case.json`` holds
    the same scene and seed (verified by content, not by the file's presence)
    and reruns any other from scratch.

Observables (SI) of the last output frame: ``z_mean`` (mean centre height,
m), ``deposited_fraction`` (fraction connected to the substrate through
touching particles, :func:`sim.analysis.deposited_mask`; NaN without a
bottom wall), ``mean_speed`` (m/s); ``D_xy`` and ``D_xy_err`` (m^2/s, the
in-plane diffusion coefficient from the whole trajectories by
:func:`ptrack.msd.estimate_diffusion`, only for scenes at T > 0 without pair
forces, where the motion is diffusive; NaN otherwise); ``wall_time_s`` of
the run.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import json
import math
import shutil
import socket
import time
import tomllib
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import pandas as pd

from ptrack.errors import UserError, atomic_output

CASE_FILE = "case.json"
OBSERVABLES = ("z_mean", "deposited_fraction", "mean_speed", "D_xy", "D_xy_err", "n_frames", "wall_time_s")


# --------------------------------------------------------------------------- the grid
def parse_set(spec: str) -> tuple[str, list]:
    """``"KEY=V1,V2"`` -> ``(KEY, [V1, V2])`` with TOML values (bare words as strings)."""
    if "=" not in spec:
        raise UserError(f"--set {spec!r} has no '='", "write --set KEY=V1,V2,... (e.g. --set fields.E=[0,0,-1e4])")
    key, _, text = spec.partition("=")
    key = key.strip()
    parts = key.split(".")
    if not key or len(parts) > 2 or not all(parts) or (len(parts) == 1 and key != "seed"):
        raise UserError(f"--set key {key!r} is not a scene key",
                        "give section.key as in the scene TOML (e.g. particles.count, fields.E) or seed")
    if not text.strip():
        raise UserError(f"--set {key}= has no values", "give one or more comma-separated values")
    try:
        values = tomllib.loads(f"v = [{text}]")["v"]
    except tomllib.TOMLDecodeError:
        # bare words (strings without quotes); a list value needs TOML syntax
        try:
            values = [tomllib.loads(f"v = {w.strip()}")["v"] if _is_toml(w) else w.strip() for w in text.split(",")]
        except tomllib.TOMLDecodeError as exc:
            raise UserError(f"--set {key}={text} is not a list of values: {exc}",
                            'separate values by commas; write vectors as [x,y,z] and strings as words or "..."')
    if not values or any(isinstance(v, str) and not v for v in values):
        raise UserError(f"--set {key}={text} has an empty value", "give one or more comma-separated values")
    return key, values


def _is_toml(word: str) -> bool:
    try:
        tomllib.loads(f"v = {word.strip()}")
        return True
    except tomllib.TOMLDecodeError:
        return False


def set_key(raw: dict, key: str, value) -> dict:
    """Copy of the scene dict ``raw`` with the dotted ``key`` set to ``value``."""
    out = copy.deepcopy(raw)
    if "." not in key:
        out[key] = value
        return out
    sec, k = key.split(".")
    if sec in out and not isinstance(out[sec], dict):
        raise UserError(f"--set key {key!r}: scene entry {sec!r} is a value, not a section",
                        f"set {sec} itself (--set {sec}=...)")
    out.setdefault(sec, {})[k] = value
    return out


def _json_safe(v):
    return [_json_safe(x) for x in v] if isinstance(v, (list, tuple)) else v


def _fingerprint(resolved: dict) -> str:
    return hashlib.sha256(json.dumps(resolved, sort_keys=True, default=str).encode()).hexdigest()


@dataclasses.dataclass
class Case:
    """One run of the sweep: a grid point and a replicate."""
    index: int
    point: int
    replicate: int
    values: dict          # swept key -> value
    raw: dict             # the scene dict of the variant
    seed: int
    folder: Path
    fingerprint: str      # of the resolved scene + seed: what a done marker must match
    source: str | None = None


def replicate_seed(seed: int, r: int) -> int:
    """Seed of replicate ``r``: the scene's own for r = 0, else ``case_seed(seed, r)``."""
    from sim.studies._dask import case_seed

    return int(seed) if r == 0 else case_seed(int(seed), int(r))


def build_cases(raw: dict, sets: list[tuple[str, list]], replicates: int, out: Path, source: str | None = None,
                quick: bool = False) -> list[Case]:
    """Every (grid point, replicate) run, each variant validated by :func:`sim.scene.scene_from_dict`.

    ``quick``: every run is cut to a tenth of ``time.final`` (at least two
    output intervals), for a fast check of a sweep.

    Raises
    ------
    UserError
        A repeated key, or a key/value the scene validator refuses (naming
        the ``--set`` it came from); raised before anything is run or written.
    """
    from sim.scene import scene_from_dict

    if replicates < 1:
        raise UserError(f"--replicates {replicates} is below 1", "give 1 or more replicates")
    keys = [k for k, _ in sets]
    dup = [k for k in keys if keys.count(k) > 1]
    if dup:
        raise UserError(f"--set {dup[0]} is given twice", "give each key once, with all its values")
    if "seed" in keys and replicates > 1:
        raise UserError("--set seed together with --replicates > 1",
                        "sweep the seed or use replicates, not both (replicates derive their own seeds)")
    cases = []
    grid = list(itertools.product(*[v for _, v in sets])) if sets else [()]
    for p, combo in enumerate(grid):
        variant = raw
        values = {}
        for (k, _), v in zip(sets, combo):
            variant = set_key(variant, k, v)
            values[k] = v
        if quick:
            t = variant.get("time", {})
            if isinstance(t, dict) and isinstance(t.get("final"), (int, float)) and isinstance(
                    t.get("output_interval"), (int, float)) and t["output_interval"] > 0:
                variant = set_key(variant, "time.final", max(2 * t["output_interval"], 0.1 * t["final"]))
        try:
            scene = scene_from_dict(variant, source=source)
        except UserError as exc:
            what = ", ".join(f"{k}={json.dumps(_json_safe(v))}" for k, v in values.items()) or "the scene"
            raise UserError(f"sweep case {what}: {exc.cause}", exc.fix) from None
        for r in range(replicates):
            seed = replicate_seed(scene.seed, r)
            resolved = dataclasses.replace(scene, seed=seed).to_dict()
            resolved.pop("source", None)  # the content counts, not where the scene file lies
            cases.append(Case(index=len(cases), point=p, replicate=r, values=values, raw=variant, seed=seed,
                              folder=out / f"case_{p:04d}_r{r:02d}", fingerprint=_fingerprint(resolved),
                              source=source))
    return cases


def load_done(case: Case) -> dict | None:
    """The stored row of a finished case if its ``case.json`` matches the case (scene and seed), else None."""
    f = case.folder / CASE_FILE
    try:
        d = json.loads(f.read_text())
    except (OSError, ValueError):
        return None
    if d.get("fingerprint") != case.fingerprint or d.get("seed") != case.seed or d.get("status") != "ok":
        return None
    return d.get("row")


# --------------------------------------------------------------------------- one run
def _unwrap(df: pd.DataFrame, box, periodic) -> pd.DataFrame:
    """Undo periodic wrapping per particle: a frame-to-frame step over half the box is a wrap (m)."""
    df = df.sort_values(["particle", "frame"]).reset_index(drop=True)
    pid = df["particle"].to_numpy()
    for ax, L, per in zip("xyz", box, periodic):
        if per:
            d = df.groupby("particle")[ax].diff().fillna(0.0).to_numpy()
            jumps = pd.Series(-L * np.round(d / L)).groupby(pid).cumsum().to_numpy()
            df[ax] = df[ax].to_numpy() + jumps
    return df


def observables(traj_path: Path, scene) -> dict:
    """The sweep's observables of one run (see the module docstring)."""
    from ptrack.table import read_table
    from sim.analysis import deposited_mask

    df = read_table(traj_path, validate_table=False)
    last = df[df["frame"] == df["frame"].max()]
    pos = last[["x", "y", "z"]].to_numpy()
    rad = last["radius"].to_numpy()
    v = last[["vx", "vy", "vz"]].to_numpy()
    box = np.asarray(scene.domain.size, dtype=float)
    periodic = (scene.boundaries.x == "periodic", scene.boundaries.y == "periodic", False)
    out = {"z_mean": float(pos[:, 2].mean()), "mean_speed": float(np.linalg.norm(v, axis=1).mean()),
           "deposited_fraction": math.nan, "D_xy": math.nan, "D_xy_err": math.nan,
           "n_frames": int(df["frame"].nunique())}
    if scene.boundaries.bottom_wall:
        wrapped = pos.copy()
        for a in range(2):
            if periodic[a]:
                wrapped[:, a] %= box[a]
        out["deposited_fraction"] = float(deposited_mask(wrapped, rad, length=box, periodic=periodic).mean())
    pair = scene.interactions is not None and getattr(scene.interactions, "any_pair_force", False)
    if scene.kT > 0 and not pair and out["n_frames"] >= 4:
        from ptrack.msd import estimate_diffusion

        tr = _unwrap(df[["frame", "t", "particle", "x", "y", "z"]], box, periodic)
        tr.attrs.update(df.attrs)
        res = estimate_diffusion(tr, axes=("xy",), motion_blur=0.0, n_boot=0)
        out["D_xy"], out["D_xy_err"] = float(res.D["xy"]), float(res.D_err["xy"])
    return out


def run_case(case: Case) -> dict:
    """Run one case (task function): skip it if done, else run, measure, write ``case.json`` atomically."""
    row = load_done(case)
    if row is not None:
        return dict(row, skipped=True)
    from sim.run import run_scene
    from sim.scene import scene_from_dict

    if case.folder.exists():  # an unfinished or different earlier run: start clean
        shutil.rmtree(case.folder)
    case.folder.mkdir(parents=True)
    scene = scene_from_dict(case.raw, source=case.source)
    t0 = time.perf_counter()
    base = {"case": case.index, "point": case.point, "replicate": case.replicate, "seed": case.seed,
            **{k: _json_safe(v) for k, v in case.values.items()}, "folder": case.folder.name}
    try:
        res = run_scene(scene, case.folder / "run", seed=case.seed, progress=False)
    except UserError as exc:  # e.g. a blow-up in this variant: report it in the table, rerun on resume
        return dict(base, status=f"failed: {exc.cause}", **{k: math.nan for k in OBSERVABLES})
    obs = observables(res.trajectories, scene)
    row = dict(base, status="ok", **obs, wall_time_s=time.perf_counter() - t0)
    with atomic_output(case.folder / CASE_FILE, "w") as fh:
        json.dump({"fingerprint": case.fingerprint, "seed": case.seed, "status": "ok",
                   "values": {k: _json_safe(v) for k, v in case.values.items()}, "row": row}, fh, indent=2,
                  default=float)
    return dict(row, skipped=False)


# --------------------------------------------------------------------------- the sweep
def check_scheduler(address: str, timeout: float = 3.0) -> None:
    """Fail fast (UserError) if nothing listens at the dask scheduler ``address`` (tcp://host:port)."""
    u = urlparse(address if "://" in address else f"tcp://{address}")
    if u.scheme not in ("tcp", "tls") or not u.hostname or not u.port:
        raise UserError(f"--scheduler {address!r} is not a scheduler address", "give tcp://HOST:PORT (e.g. tcp://127.0.0.1:8786)")
    try:
        socket.create_connection((u.hostname, u.port), timeout=timeout).close()
    except OSError as exc:
        raise UserError(f"cannot reach the dask scheduler at {address}: {exc.strerror or exc}",
                        "start it (dask scheduler) or check the address, or leave out --scheduler for a local cluster")


def run_sweep(scene_path, sets: list[str], out, replicates: int = 1, scheduler: str | None = None,
              workers: int | None = None, quick: bool = False, progress: bool = True,
              use_dask: bool = True) -> pd.DataFrame:
    """Run the grid of ``sets`` over the scene file; write and return the summary table.

    Parameters
    ----------
    scene_path : path-like
        Scene TOML file.
    sets : list of str
        ``KEY=V1,V2,...`` specifications (see the module docstring).
    out : path-like
        Sweep folder: ``case_PPPP_rRR/`` per run, ``sweep.json``,
        ``summary.csv`` and ``summary.parquet``.
    replicates : int
        Runs per grid point, with distinct deterministic seeds.
    scheduler : str, optional
        Address of a running dask scheduler (default: a local cluster).
    workers : int, optional
        Threads of the local cluster.
    quick : bool
        Each run cut to a tenth of ``time.final``.
    use_dask : bool
        False: run the cases serially in this process.

    Returns
    -------
    DataFrame
        One row per run: case, point, replicate, seed, the swept keys,
        folder, status, the observables (SI), skipped (True if resumed).
    """
    from sim.scene import load_scene
    from sim.studies._dask import run_cases

    scene_path = Path(scene_path).resolve()
    base = load_scene(scene_path)  # validates the file itself (clear error for a bad scene)
    with open(scene_path, "rb") as fh:
        raw = tomllib.load(fh)
    parsed = [parse_set(s) for s in sets]
    out = Path(out).resolve()  # resolved on the client: workers may run elsewhere
    cases = build_cases(raw, parsed, int(replicates), out, source=base.source, quick=quick)
    if scheduler:
        check_scheduler(scheduler)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_output(out / "sweep.json", "w") as fh:
        json.dump({"scene": str(scene_path), "sets": [[k, _json_safe(v)] for k, v in parsed],
                   "replicates": int(replicates), "quick": bool(quick), "n_runs": len(cases)}, fh, indent=2)
    rows = run_cases(run_case, cases, scheduler=scheduler, use_dask=use_dask, workers=workers, progress=progress,
                     desc="sweep")
    table = pd.DataFrame(rows)
    for k, _ in parsed:  # vectors as text in the table (Parquet needs one type per column)
        if table[k].map(lambda v: isinstance(v, list)).any():
            table[k] = table[k].map(lambda v: json.dumps(v))
    with atomic_output(out / "summary.csv", "w") as fh:
        table.to_csv(fh, index=False)
    with atomic_output(out / "summary.parquet", None) as tmp:
        table.to_parquet(tmp, index=False)
    return table
