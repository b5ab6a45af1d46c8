"""Crash safety of `ptrack simulate` (DEM): kill the process, resume, get the uninterrupted run's table.

Each case runs the CLI in a subprocess, waits until a checkpoint exists, kills it (SIGKILL, SIGTERM,
SIGINT, or SIGKILL twice with a resume in between), resumes with --resume and compares every frame
with an uninterrupted run, value for value.
"""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

SCENE = """
seed = 1
[particles]
count = 150
radius = 0.05
density = 1540.0
[fluid]
density = 0.0
viscosity = 1.0e-12
temperature = 0.0
[gravity]
g = [0.0, 0.0, -109.81]
buoyancy = false
[domain]
size = [1.0, 1.0, 1.0]
placement_z = [0.05, 0.6]
[boundaries]
x = "periodic"
y = "periodic"
[time]
dt = 1.0e-6
final = 0.05
output_interval = 0.0005
[contact]
model = "hooke"
kn = 1.0e9
restitution = 0.3
skin = 0.01
checkpoint_every = 4
[friction]
mu = 0.4
"""


def _table(path):
    from ptrack.table import read_table

    return read_table(path, validate_table=False)


def _cli(*args):
    return [sys.executable, "-m", "ptrack", "simulate", *args, "--quiet"]


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("scene") / "small.toml"
    p.write_text(SCENE)
    return p


@pytest.fixture(scope="module")
def reference_dir(scene_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    r = subprocess.run(_cli(str(scene_file), "--out", str(out)), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return out


@pytest.fixture(scope="module")
def reference(reference_dir):
    return _table(reference_dir / "trajectories.parquet")


def _checkpoint_frame(out):
    from sim.checkpoint import load_checkpoint

    try:
        return int(load_checkpoint(out / "checkpoint.npz")[1]["frame"])
    except Exception:  # not there yet, or being renamed into place
        return -1


def _run_and_kill(scene_file, out, sig, resume=False, after_frame=0):
    """Start a run, wait until a checkpoint past ``after_frame`` exists, send ``sig``; returns the exit code."""
    args = _cli(str(scene_file), "--out", str(out)) + (["--resume"] if resume else [])
    p = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while _checkpoint_frame(out) <= after_frame:
        if p.poll() is not None or time.time() - t0 > 300:
            break
        time.sleep(0.01)
    assert p.poll() is None, "the run ended before it could be killed: " + (p.stderr.read() or "")
    p.send_signal(sig)
    rc = p.wait(timeout=60)
    return rc, p.stderr.read()


def _assert_same(df, ref, frames=101):
    assert not df.attrs["ptrack"].get("incomplete")
    key = ["frame", "particle"]
    a = df.sort_values(key).reset_index(drop=True)
    b = ref.sort_values(key).reset_index(drop=True)
    assert len(a) == len(b) and a["frame"].nunique() == b["frame"].nunique() == frames
    pd.testing.assert_frame_equal(a[b.columns], b, check_exact=True)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT], ids=["kill", "term", "int"])
def test_kill_then_resume_gives_every_frame_of_the_uninterrupted_run(scene_file, reference, tmp_path, sig):
    rc, err = _run_and_kill(scene_file, tmp_path, sig)
    if sig == signal.SIGKILL:
        assert rc == -signal.SIGKILL
    else:
        # stopped cleanly at the next kernel return: exit 130, one line, no traceback
        assert rc == 130, err
        assert "Traceback" not in err and "SystemError" not in err
        part = _table(tmp_path / "trajectories.parquet")  # what was complete, marked incomplete
        assert part.attrs["ptrack"]["incomplete"].startswith("interrupted")
        assert part["frame"].max() >= _checkpoint_frame(tmp_path)
    r = subprocess.run(_cli(str(scene_file), "--out", str(tmp_path), "--resume"), capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    _assert_same(_table(tmp_path / "trajectories.parquet"), reference)


def test_double_kill_then_resume(scene_file, reference, tmp_path):
    rc, _ = _run_and_kill(scene_file, tmp_path, signal.SIGKILL)
    first = _checkpoint_frame(tmp_path)
    assert rc == -signal.SIGKILL and first > 0
    rc, _ = _run_and_kill(scene_file, tmp_path, signal.SIGKILL, resume=True, after_frame=first)
    assert rc == -signal.SIGKILL and _checkpoint_frame(tmp_path) > first
    r = subprocess.run(_cli(str(scene_file), "--out", str(tmp_path), "--resume"), capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    _assert_same(_table(tmp_path / "trajectories.parquet"), reference)


def _files(folder):
    return {p.relative_to(folder): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


def test_resume_of_a_finished_run_is_a_no_op(scene_file, reference_dir, reference, capsys):
    """--resume of a DEM run that finished: exit 0, "run already complete", nothing computed or rewritten;
    with another seed it is a different run and is refused as before."""
    from ptrack.cli import main

    before = _files(reference_dir)
    assert main(["simulate", str(scene_file), "--out", str(reference_dir), "--resume", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "run already complete" in err and f"all {reference['frame'].nunique()} frames" in err, err
    assert _files(reference_dir) == before
    assert main(["simulate", str(scene_file), "--out", str(reference_dir), "--resume", "--seed", "2", "--quiet"]) == 2
    assert "different scene" in capsys.readouterr().err
    assert _files(reference_dir) == before


def test_resume_refuses_another_seed_and_keeps_scene_json(scene_file, tmp_path):
    rc, _ = _run_and_kill(scene_file, tmp_path, signal.SIGKILL)
    assert rc == -signal.SIGKILL
    before = (tmp_path / "scene.json").read_bytes()
    files = sorted(os.listdir(tmp_path))
    r = subprocess.run(_cli(str(scene_file), "--out", str(tmp_path), "--resume", "--seed", "2"),
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 2
    assert r.stderr.startswith("error: ") and "different scene" in r.stderr and "Traceback" not in r.stderr
    assert (tmp_path / "scene.json").read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == files


def test_resume_without_checkpoint_is_refused_at_once(scene_file, tmp_path):
    out = tmp_path / "new"
    t0 = time.time()
    r = subprocess.run(_cli(str(scene_file), "--out", str(out), "--resume"), capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 2 and "no checkpoint" in r.stderr
    assert not out.exists()  # nothing written, not even an empty folder
    assert time.time() - t0 < 60  # (no wall-time assertion on the run: only that it did not start one)


def test_new_run_moves_the_old_run_aside_keeping_one_generation(scene_file, tmp_path):
    from ptrack.errors import UserError  # noqa: F401  (the CLI's error type)
    from sim.run import run_scene
    from sim.scene import scene_from_dict

    import tomllib

    raw = tomllib.loads(SCENE)
    raw["time"]["final"] = 0.002
    run_scene(scene_from_dict(raw), tmp_path, progress=False)
    first = _table(tmp_path / "trajectories.parquet")
    raw["seed"] = 2
    run_scene(scene_from_dict(raw), tmp_path, progress=False)
    second = _table(tmp_path / "trajectories.parquet")
    moved = _table(tmp_path / "previous" / "trajectories.parquet")
    pd.testing.assert_frame_equal(moved, first)
    run_scene(scene_from_dict(raw), tmp_path, progress=False)  # a third run: one generation kept
    pd.testing.assert_frame_equal(_table(tmp_path / "previous" / "trajectories.parquet"), second)
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_dir()) == ["previous"]
    assert json.loads((tmp_path / "scene.json").read_text())["scene"]["seed"] == 2
    assert not np.array_equal(second[["x", "y"]].to_numpy(), first[["x", "y"]].to_numpy())
    assert not (tmp_path / ".segments").exists()


FREE = """
seed = 4
[particles]
count = 400
radius = 1.0e-7
density = 2200.0
charge = -1.0e-17
[fluid]
temperature = 293.0
[fields]
E = [0.0, 0.0, -1.0e3]
[domain]
size = [1.0e-5, 1.0e-5, 2.0e-5]
[time]
dt = 1.0e-9
final = 1.0
output_interval = 1.0e-2
[integrator]
kind = "ou_exact"
"""


def test_ctrl_c_stops_a_free_particle_run_inside_its_kernels(tmp_path):
    """4e11 particle-steps (hours); SIGINT must end it at the next kernel return with exit 130."""
    scene = tmp_path / "free.toml"
    scene.write_text(FREE)
    out = tmp_path / "out"
    # --max-hours: the run is meant to be far too long (it is refused by default, with its ~55 h estimate)
    p = subprocess.Popen(_cli(str(scene), "--out", str(out), "--max-hours", "1000"), stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    # frame 0 is streamed into the first table segment before the first kernel call
    while not list(out.glob(".segments/*.part")) and p.poll() is None and time.time() - t0 < 300:
        time.sleep(0.05)
    assert p.poll() is None and time.time() - t0 < 300
    time.sleep(1.0)  # inside the first kernel call
    p.send_signal(signal.SIGINT)
    rc = p.wait(timeout=120)  # uninterrupted, the first group of frames alone takes minutes
    err = p.stderr.read()
    assert rc == 130 and "Traceback" not in err and "SystemError" not in err, err
    df = _table(out / "trajectories.parquet")  # frame 0 at least, readable, marked incomplete
    assert df.attrs["ptrack"]["incomplete"].startswith("interrupted") and df["frame"].min() == 0


def test_particle_blocks_give_the_same_numbers_as_one_call():
    import tomllib

    from sim.driver import WallClockChunker
    from sim.integrate import choose_integrator
    from sim.run import Stepper
    from sim.scene import scene_from_dict
    from sim.state import build_state, constant_force

    raw = tomllib.loads(FREE)
    raw["time"].update(dt=1e-6, final=1e-3, output_interval=1e-4)
    res = []
    for kind in ("ou_exact", "overdamped", "trapezoidal"):
        raw["integrator"] = {"kind": kind, "phi": 0.5 if kind == "trapezoidal" else 0.0}
        for chunker in (None, WallClockChunker(first=30 * 100, seconds=1e9, limit=3000)):
            sc = scene_from_dict(raw)
            st = build_state(sc)
            fc = constant_force(sc, st)
            stepper = Stepper(sc, st, fc, choose_integrator(sc, st, fc))
            res.append(stepper.advance(5, chunker=chunker, poll=lambda: None)[0])
        np.testing.assert_array_equal(res[-1], res[-2])


def test_absurd_cost_refused_up_front_with_the_reason(tmp_path):
    import tomllib

    from ptrack.errors import UserError
    from sim.run import run_scene
    from sim.scene import scene_from_dict

    raw = tomllib.loads(FREE)
    raw["fields"]["E"] = [0.0, 0.0, -1.0e12]
    raw["time"].pop("dt")
    raw["integrator"]["kind"] = "auto"
    out = tmp_path / "never"
    with pytest.raises(UserError, match="Reynolds number reaches") as exc:
        run_scene(scene_from_dict(raw), out, progress=False)
    assert "particle-steps" in str(exc.value)
    assert not out.exists()


def test_unstable_dt_refused_without_leaving_a_folder(tmp_path):
    import tomllib

    from ptrack.errors import UserError
    from sim.run import run_scene
    from sim.scene import scene_from_dict

    raw = tomllib.loads(FREE)
    raw["time"].update(dt=1e-6, final=1e-3, output_interval=1e-4)
    raw["integrator"] = {"kind": "trapezoidal", "phi": 0.0}
    out = tmp_path / "never"
    with pytest.raises(UserError, match="unstable"):
        run_scene(scene_from_dict(raw), out, progress=False)
    assert not out.exists()


def test_free_particle_run_interrupted_then_resumed_equals_uninterrupted(tmp_path, monkeypatch):
    """Free particles checkpoint too (counter-based random numbers): an interrupt after three chunks of
    frames, then resume, gives the uninterrupted table; a resume with another seed is refused."""
    import tomllib

    import sim.run as run_mod
    from ptrack.errors import UserError
    from sim.scene import scene_from_dict

    raw = tomllib.loads(FREE)
    raw["particles"]["count"] = 50
    raw["time"].update(dt=1e-7, final=1e-4, output_interval=1e-6)
    sc = scene_from_dict(raw)
    kw = dict(progress=False, max_rows_per_chunk=500, checkpoint_seconds=0.0)  # 10 frames a chunk
    run_mod.run_scene(sc, tmp_path / "ref", **kw)
    ref = _table(tmp_path / "ref" / "trajectories.parquet")

    orig = run_mod.Stepper.advance
    calls = {"n": 0}

    def interrupted(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt("test")
        return orig(self, *a, **k)

    monkeypatch.setattr(run_mod.Stepper, "advance", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_mod.run_scene(sc, tmp_path / "run", **kw)
    monkeypatch.setattr(run_mod.Stepper, "advance", orig)
    part = _table(tmp_path / "run" / "trajectories.parquet")
    assert part["frame"].max() == 30 and part.attrs["ptrack"]["incomplete"].startswith("interrupted")
    with pytest.raises(UserError, match="different scene"):
        run_mod.run_scene(sc, tmp_path / "run", seed=9, resume=True, **kw)
    run_mod.run_scene(sc, tmp_path / "run", resume=True, **kw)
    _assert_same(_table(tmp_path / "run" / "trajectories.parquet"), ref, frames=101)


def _free_scene(**time):
    import tomllib

    from sim.scene import scene_from_dict

    raw = tomllib.loads(FREE)
    raw["particles"]["count"] = 20
    raw["time"].update(dt=1e-7, final=1e-4, output_interval=1e-6, **time)
    return scene_from_dict(raw)


def test_free_particle_resume_of_a_finished_run_is_a_no_op(tmp_path):
    from sim.run import run_complete, run_scene
    from sim.checkpoint import scene_fingerprint

    sc = _free_scene()
    first = run_scene(sc, tmp_path, progress=False)
    assert not first.already_complete and run_complete(tmp_path, scene_fingerprint(sc.to_dict())) == 101
    before = _files(tmp_path)
    again = run_scene(sc, tmp_path, progress=False, resume=True)
    assert again.already_complete and again.n_frames == 101 and again.choice is None
    assert _files(tmp_path) == before


def test_interrupt_before_the_first_commit_leaves_no_segment_folder(tmp_path, monkeypatch):
    """Ctrl-C before any checkpoint: the table (frame 0, marked incomplete) stays, no empty .segments."""
    import sim.run as run_mod

    def interrupted(self, *a, **k):
        raise KeyboardInterrupt("test")

    monkeypatch.setattr(run_mod.Stepper, "advance", interrupted)
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_mod.run_scene(_free_scene(), out, progress=False, checkpoint_seconds=1e9)
    assert sorted(p.name for p in out.iterdir()) == ["scene.json", "trajectories.parquet"]
    part = _table(out / "trajectories.parquet")
    assert part["frame"].tolist() == [0] * 20 and part.attrs["ptrack"]["incomplete"].startswith("interrupted")


def test_a_full_disk_at_the_start_leaves_no_folder(tmp_path, monkeypatch):
    """ENOSPC on the first write (scene.json): the OSError reaches the CLI (one line there), and the folders
    the run made (two levels) are gone; no tmpfs needed."""
    import errno

    import sim.run as run_mod

    real = run_mod.atomic_output

    def full(path, mode="wb"):
        if Path(path).name == "scene.json":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, mode)

    monkeypatch.setattr(run_mod, "atomic_output", full)
    with pytest.raises(OSError):
        run_mod.run_scene(_free_scene(), tmp_path / "a" / "b", progress=False)
    assert list(tmp_path.iterdir()) == []


def test_cost_estimate_uses_the_run_s_dt_and_the_kernel_s_rate():
    """E = 1e12 V/m on 20 free particles (the fault suite's scene): 8e10 particle-steps, below the old
    limit of 1e12 particle-steps but ~15 h for the trapezoidal kernel: refused with the estimate; the same
    allowed with a larger budget."""
    import tomllib

    from ptrack.errors import UserError
    from sim.integrate import choose_integrator
    from sim.run import PARTICLE_STEPS_PER_S, Stepper, check_cost
    from sim.scene import scene_from_dict
    from sim.state import build_state, constant_force

    raw = tomllib.loads(FREE)
    raw["particles"].update(count=20, radius=2.0e-7)
    raw["particles"].pop("charge")
    raw["particles"]["charge_per_mass"] = -1.0
    raw["fields"]["E"] = [0.0, 0.0, 1.0e12]
    raw["time"] = {"dt": "auto", "final": 5.0e-2, "output_interval": 1.0e-3}
    raw["integrator"]["kind"] = "auto"
    sc = scene_from_dict(raw)
    st = build_state(sc)
    fc = constant_force(sc, st)
    ch = choose_integrator(sc, st, fc)
    assert ch.kind == "trapezoidal"
    cost = 20 * 50 * ch.steps_per_output
    assert 1e10 < cost < 1e12
    with pytest.raises(UserError, match="particle-steps") as exc:
        check_cost(20, 50, ch)
    hours = cost / PARTICLE_STEPS_PER_S["trapezoidal"] / 3600
    assert f"about {hours:.3g} h" in str(exc.value) and "--max-hours" in str(exc.value)
    assert check_cost(20, 50, ch, max_hours=2 * hours) == cost
    # the estimate counts the steps of the dt the kernels take: steps x dt = one output interval
    assert ch.dt * ch.steps_per_output == pytest.approx(sc.time.output_interval, rel=1e-12)
