"""Fault injection: bad files, bad numbers, a full or read-only disk and Ctrl-C, through the command line.

The corpus is built at test time (a small rendered movie, its truth table and
a small scene, then broken copies of each). Every case runs
``ptrack.cli.main(argv)`` in-process (fast), in a folder of its own, and must
end with exit status 2 (130 for Ctrl-C), exactly one line on stderr starting
with ``error:``, no traceback, and no file or folder left behind. Full-disk
and read-only cases use a small tmpfs (``mount -t tmpfs``; skipped where it
cannot be mounted); Ctrl-C cases run in a subprocess.

The cases are plain data (:data:`CASES`), so ``bench/bench_faults.py`` runs
the same suite and prints its figures per fault class. A case that fails
because of a bug in a module another helper owns is marked
``xfail(strict=True)`` naming that file: a fix makes it pass, and the strict
mark then fails until it is removed.
"""
from __future__ import annotations

import contextlib
import io
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

# ---------------------------------------------------------------------------------------------------
# corpus


SCENE = """seed = 3
[particles]
count = 20
radius = 2.0e-7
density = 2200.0
[fluid]
density = 1000.0
viscosity = 1.0e-3
temperature = 293.0
[gravity]
enabled = false
[domain]
size = [1.0e-5, 1.0e-5, 1.0e-5]
[boundaries]
x = "open"
y = "open"
bottom_wall = false
[time]
dt = "auto"
final = {final}
output_interval = 1.0e-3
[integrator]
kind = "auto"
"""


# a small DEM deposition (seed example 1 scaled down: 80 spheres, 13 frames, a checkpoint every 3 frames)
DEM_SCENE = """seed = 1
[particles]
count = 80
radius = 0.05
density = 1540.0
charge_per_mass = -1.0
initial_velocity = "zero"
[fluid]
density = 1.2754
viscosity = 18.03e-6
temperature = 0.0
[fields]
E = [0.0, 0.0, 100.0]
[gravity]
enabled = true
g = [0.0, 0.0, -9.81]
buoyancy = true
[domain]
size = [0.8, 0.8, 0.5]
placement_z = [0.0, 0.5]
[boundaries]
x = "open"
y = "open"
bottom_wall = true
[time]
dt = 1.0e-6
final = {final}
output_interval = 0.002
[contact]
model = "power"
K = 1.0e9
exponent = 2.0
damping = 1.0e8
checkpoint_every = 3
[bonding]
K_nb = 1.0e8
K_rb = 1.0e5
exponent = 2.0
critical_strain = 0.02
[friction]
K_f = 1.0e9
mu_s = 0.4
mu_d = 0.3
[walls]
K = 1.0e11
exponent = 2.0
K_nb = 1.0e10
K_rb = 1.0e7
[nearfield]
model = "seed"
alpha1 = 0.5
alpha2 = 0.05
beta1 = 1.0
beta2 = 2.0
cutoff = 0.15
"""


def build_corpus(root: Path) -> dict:
    """Write the inputs (good and broken) under ``root``; return their paths by name."""
    import tifffile

    from ptrack.table import make_table, write_table
    from sim import render

    root.mkdir(parents=True, exist_ok=True)
    c: dict[str, Path] = {}
    rng = np.random.default_rng(1)
    cam = render.Camera(photons=3000)
    px = render.sample_pixel_size(render.Optics(), cam.pixel_pitch)
    n, T = 6, 25
    x = (rng.uniform(12, 52, n) * px)[:, None] + rng.normal(0, 4e-8, (n, T)).cumsum(1)
    y = (rng.uniform(12, 52, n) * px)[:, None] + rng.normal(0, 4e-8, (n, T)).cumsum(1)
    fr = np.tile(np.arange(T), n)
    tab = make_table(fr, fr * 0.1, np.repeat(np.arange(n), T), x.ravel(), y.ravel(), np.zeros(n * T),
                     meta={"frame_interval": 0.1})
    info = render.render_movie(tab, root / "good", shape=(64, 64), camera=cam, seed=2, progress=False)
    c["movie"] = Path(info["movie"])
    c["table"] = Path(info["truth"])
    good = c["movie"].read_bytes()

    def put(name, data: bytes):
        p = root / name
        p.write_bytes(data)
        c[name.split(".")[0]] = p

    # movies
    put("truncated_half.tif", good[: len(good) // 2])
    put("truncated_tail.tif", good[:-3000])
    put("header_only.tif", good[:16])
    put("random_bytes.tif", rng.integers(0, 256, 20000, dtype=np.uint8).tobytes())
    put("empty.tif", b"")
    put("text.tif", b"this is not a TIFF file\n" * 50)
    bad = bytearray(good)
    bad[8:4000] = rng.integers(0, 256, 3992, dtype=np.uint8).tobytes()
    put("corrupt_start.tif", bytes(bad))
    with tifffile.TiffFile(c["movie"]) as tf:
        frames = tf.asarray()

    def tif(name, arr, **kw):
        p = root / name
        tifffile.imwrite(p, arr, **kw)
        c[name.split(".")[0]] = p

    meta = dict(imagej=True, resolution=(1 / 0.1, 1 / 0.1), metadata={"unit": "um", "finterval": 0.1, "axes": "TYX"})
    tif("complex.tif", frames.astype(np.complex64))
    nanmov = frames.astype(np.float32)
    nanmov[3, 10:20, 10:20] = np.nan
    tif("nan_pixels.tif", nanmov, **meta)
    tif("one_pixel.tif", frames[:, :1, :1], **meta)
    tif("two_by_two.tif", frames[:, :2, :2], **meta)
    tif("single_frame.tif", frames[:1], **meta)
    tif("rgb.tif", np.stack([frames] * 3, axis=-1).astype(np.uint8), photometric="rgb")
    tif("five_d.tif", frames[:4, None, None].repeat(2, axis=1).repeat(2, axis=2))
    tif("constant.tif", np.full_like(frames, 100), **meta)
    (root / "no_frames").mkdir()
    c["no_frames"] = root / "no_frames"
    c["missing_movie"] = root / "nope.tif"

    # tables
    import pandas as pd

    df = pd.read_parquet(c["table"])

    def csv(name, frame: pd.DataFrame | str):
        p = root / name
        if isinstance(frame, str):
            p.write_text(frame)
        else:
            frame.to_csv(p, index=False)
        c[name.split(".")[0]] = p

    csv("no_x.csv", df.drop(columns=["x"]))
    csv("nan_x.csv", df.assign(x=np.where(df.index == 7, np.nan, df["x"])))
    csv("dup_rows.csv", pd.concat([df, df.iloc[:3]]))
    csv("frac_frames.csv", df.assign(frame=df["frame"] + 0.5))
    csv("text_x.csv", df.assign(x="left"))
    csv("header_only_table.csv", "frame,t,particle,x,y,z\n")
    csv("empty_table.csv", "")
    csv("negative_frames.csv", df.assign(frame=df["frame"] - 10))
    csv("inf_t.csv", df.assign(t=np.where(df.index == 2, np.inf, df["t"])))
    csv("one_frame.csv", df[df["frame"] == 0])
    csv("flat_z.csv", df.assign(z=2.0e-6))  # heights given, all equal: nothing to measure along z
    csv("huge_coords.csv", df.assign(x=df["x"] * 1e300 / df["x"].abs().max(), y=df["y"] * 1e300 / df["y"].abs().max()))
    tb = c["table"].read_bytes()
    put("truncated_table.parquet", tb[: len(tb) // 2])
    put("random_table.parquet", rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
    c["missing_table"] = root / "nope.parquet"
    write_table(tab, root / "table_ok.parquet")
    c["table_ok"] = root / "table_ok.parquet"

    # scenes
    def scene(name, text):
        p = root / name
        p.write_text(text)
        c[name.split(".")[0]] = p

    ok = SCENE.format(final="5.0e-2")
    scene("scene_ok.toml", ok)
    scene("scene_unknown_key.toml", ok.replace("count = 20", "count = 20\ncolour = \"red\""))
    scene("scene_wrong_type.toml", ok.replace("count = 20", 'count = "many"'))
    scene("scene_negative_radius.toml", ok.replace("radius = 2.0e-7", "radius = -2.0e-7"))
    scene("scene_nan_viscosity.toml", ok.replace("viscosity = 1.0e-3", "viscosity = nan"))
    scene("scene_not_toml.toml", "this is = = not toml [\n")
    scene("scene_empty.toml", "")
    scene("scene_zero_count.toml", ok.replace("count = 20", "count = 0"))
    scene("scene_backwards_time.toml", ok.replace("final = 5.0e-2", "final = -1.0"))
    scene("scene_unknown_section.toml", ok + "\n[magic]\nstrength = 3\n")
    scene("scene_crowded.toml", ok.replace("count = 20", "count = 200000").replace("radius = 2.0e-7", "radius = 1.0e-6"))
    scene("scene_bad_dt.toml", ok.replace('dt = "auto"', "dt = 10.0"))
    c["missing_scene"] = root / "nope.toml"
    scene("scene_long.toml", SCENE.format(final="1.0e3"))
    # E = 1e12 V/m on free particles: the automatic dt would need ~1e9 steps per frame
    scene("scene_forever.toml", ok.replace("density = 2200.0", "density = 2200.0\ncharge_per_mass = -1.0")
          .replace("[gravity]", "[fields]\nE = [0.0, 0.0, 1.0e12]\n[gravity]"))
    scene("dem.toml", DEM_SCENE.format(final="0.024"))
    scene("dem_long.toml", DEM_SCENE.format(final="10.0"))
    c["movie2"] = root / "good" / "movie2.tif"
    shutil.copy(c["movie"], c["movie2"])
    return c


# ---------------------------------------------------------------------------------------------------
# cases


@dataclass
class Case:
    """One fault: the command line (with {name} for corpus paths, {out} for the case's output folder)."""

    id: str
    kind: str  # fault class: movie, table, scene, number, disk, read-only, unwritable, interrupt
    argv: list
    needs: str | None = None  # "full" | "ro" (a tmpfs), "subprocess"
    xfail: str | None = None  # reason naming the file at fault
    exit_code: int = 2
    not_words: tuple = ()  # words the message must not contain (wrong blame)
    expect: str | None = None  # the message must name this corpus input (the fault, not something else)
    deadline: float | None = None  # run in a subprocess that must end within this many seconds
    setup: list | None = None  # a command line run first (must succeed); what it writes is not left behind

    def expected_text(self, corpus: dict) -> str | None:
        if self.expect is None:
            return None
        p = corpus.get(self.expect)
        return p.name if p is not None else self.expect

    def resolve(self, corpus: dict, out: Path, mounts: dict, argv: list | None = None) -> list[str]:
        sub = {k: str(v) for k, v in corpus.items()}
        sub["out"] = str(out)
        sub.update({k: str(v) for k, v in mounts.items()})
        return [a.format(**sub) for a in (self.argv if argv is None else argv)]


def _movie_cases():
    names = ["truncated_half", "truncated_tail", "header_only", "random_bytes", "empty", "text", "corrupt_start",
             "complex", "nan_pixels", "one_pixel", "two_by_two", "single_frame", "rgb", "five_d", "constant",
             "no_frames", "missing_movie"]
    cases = [Case(f"track-{n}", "movie", ["track", "{%s}" % n, "--out", "{out}/t.parquet"],
                  not_words=("corrupt", "truncated") if n in ("one_pixel", "two_by_two", "single_frame") else (),
                  expect=n)
             for n in names]
    cases += [Case("analyze-truncated", "movie", ["analyze", "{truncated_half}", "--radius", "5e-7", "--viscosity",
                                                   "1e-3", "--temperature", "293", "--report", "{out}/rep"]),
              Case("track-glob-nothing", "movie", ["track", "{out}/*.tif", "--out", "{out}/t.parquet"]),
              Case("analyze-height-below-radius", "movie",
                   ["analyze", "{movie}", "--radius", "5e-7", "--viscosity", "1e-3", "--temperature", "293",
                    "--height", "1e-7", "--out", "{out}/t.parquet", "--report", "{out}/rep"]),
              Case("track-calib-missing", "movie", ["track", "{movie}", "--calib", "{missing_movie}",
                                                    "--out", "{out}/t.parquet"]),
              Case("track-calib-corrupt", "movie", ["track", "{movie}", "--calib", "{random_bytes}",
                                                    "--out", "{out}/t.parquet"]),
              # refused after the 2 s connect timeout (1.3 s of CPU, but 10-20 s of wall time at load 15 on 2
              # cores); dask's own 30 s wait ended in a traceback, which the one-line check catches: the
              # deadline only catches a hang
              Case("track-dask-unreachable-scheduler", "movie",
                   ["track", "{movie}", "{movie2}", "--scheduler", "tcp://127.0.0.1:9", "--out", "{out}"],
                   deadline=60.0)]
    return cases


def _table_cases():
    names = ["no_x", "nan_x", "dup_rows", "frac_frames", "text_x", "header_only_table", "empty_table",
             "negative_frames", "inf_t", "one_frame", "truncated_table", "random_table", "missing_table", "huge_coords"]
    cases = []
    for n in names:
        src = "{%s}" % n
        # a file that cannot be read as a table must be named; an empty or one-frame table need not be
        named = n if n not in ("header_only_table", "one_frame", "huge_coords") else None
        cases.append(Case(f"msd-{n}", "table", ["msd", src, "--json", "{out}/m.json", "--plot", "{out}/m.png"],
                          expect=named))
        cases.append(Case(f"velocity-{n}", "table", ["velocity", src, "--out", "{out}/v.csv", "--report", "{out}/vr"],
                          expect=named))
        if n != "one_frame":  # one frame is a fine movie
            cases.append(Case(f"render-{n}", "table", ["render", src, "--out", "{out}/r", "--shape", "32", "32"],
                              expect=named))
        cases.append(Case(f"compare-{n}", "table", ["compare", src, "{table}", "--json", "{out}/c.json"], expect=named))
    # v_z asked of a table whose z never changes (without --axes, z is skipped with a note: exit 0)
    cases.append(Case("velocity-flat_z-axes-xyz", "table", ["velocity", "{flat_z}", "--axes", "xyz", "--out",
                                                            "{out}/v.csv", "--report", "{out}/vr"], expect="flat_z"))
    return cases


def _scene_cases():
    names = ["scene_unknown_key", "scene_wrong_type", "scene_negative_radius", "scene_nan_viscosity", "scene_not_toml",
             "scene_empty", "scene_zero_count", "scene_backwards_time", "scene_unknown_section", "scene_crowded",
             "scene_bad_dt", "missing_scene"]
    cases = [Case(f"simulate-{n}", "scene", ["simulate", "{%s}" % n, "--out", "{out}/s", "--quiet"],
                  expect=n if n in ("scene_not_toml", "missing_scene") else None) for n in names]
    cases.append(Case("simulate-resume-without-checkpoint", "scene",
                      ["simulate", "{scene_ok}", "--out", "{out}/s", "--quiet", "--resume"]))
    cases.append(Case("simulate-dem-resume-without-checkpoint", "scene",
                      ["simulate", "{dem}", "--out", "{out}/s", "--quiet", "--resume"]))
    cases.append(Case("simulate-resume-with-another-scene", "scene",
                      ["simulate", "{dem_long}", "--out", "{out}/s", "--quiet", "--resume"],
                      setup=["simulate", "{dem}", "--out", "{out}/s", "--quiet"]))
    # refused before the first step (a few seconds, mostly imports on a loaded machine); unrefused it runs ~15 h
    cases.append(Case("simulate-run-that-takes-forever", "scene",
                      ["simulate", "{scene_forever}", "--out", "{out}/s", "--quiet"], deadline=60.0))
    return cases


# the smallest valid command line of each command, with the option under test appended
_BASE = {
    "track": ["{movie}"], "analyze": ["{movie}", "--radius", "5e-7", "--viscosity", "1e-3", "--temperature", "293"],
    "msd": ["{table}"], "velocity": ["{table}"], "wall": ["--radius", "1e-6", "--height", "2e-6"],
    "render": ["{table}", "--out", "{out}/r"], "render-calibration": ["--out", "{out}/c"],
    "simulate": ["{scene_ok}", "--out", "{out}/s"], "compare": ["{table}", "{table}"],
    "twin": ["{movie}", "--temperature", "293", "--viscosity", "1e-3", "--out", "{out}/t"], "sweep": ["{scene_ok}", "--out", "{out}/w"],
}


def _bad_values(rng, is_int: bool):
    """Values outside ``rng`` (a ptrack.options.Range), as command-line text."""
    vals = [] if is_int else ["nan", "inf", "-inf"]
    if rng.lo is not None:
        vals.append(str(int(rng.lo) - 1) if is_int else (f"{rng.lo:g}" if rng.lo_open else f"{rng.lo - 1:g}"))
    if rng.hi is not None:
        vals.append(str(int(rng.hi) + 1) if is_int else (f"{rng.hi:g}" if rng.hi_open else f"{rng.hi + 1:g}"))
    if rng.nonzero:
        vals.append("0")
    if is_int:
        vals.append("1.5")
    return vals


def _number_cases():
    from ptrack.cli import COMMANDS, STUDIES, command_parser
    from ptrack.options import range_for

    names = [n for n, (m, _) in COMMANDS.items() if m] + [f"study {s}" for s in STUDIES]
    cases = []
    for name in names:
        try:
            key, parser = command_parser(name)
        except Exception:  # a registered command whose module is not in this checkout
            continue
        for a in parser.numeric_actions:
            opt = max([s for s in a.option_strings if s.startswith("--")], key=len)
            rng = range_for(key, opt)
            if rng is None or a.choices:
                continue
            base = list(_BASE.get(name, []))
            if name == "wall" and opt in ("--height", "--ratio"):
                base = ["--radius", "1e-6"]
            elif opt in base:
                i = base.index(opt)
                del base[i:i + 2]
            nargs = a.nargs if isinstance(a.nargs, int) else 1
            good = {"--z-range": ["-1e-6", "1e-6"]}.get(opt, ["1"] * nargs)
            for v in _bad_values(rng, a.type is int):
                val = [v] + good[1:]
                if opt == "--z-range" and v not in ("nan", "inf", "-inf"):
                    val = ["1e-6", "-1e-6"]  # not increasing
                cases.append(Case(f"{name.replace(' ', '-')}{opt}={'_'.join(val)}", "number",
                                  name.split() + base + [opt] + val))
    return cases


_WRITERS = [  # (id, argv writing under {D}: the folder on the full / read-only / unwritable disk)
    ("track", ["track", "{movie}", "--out", "{D}/t.parquet"]),
    # the summary's folder cannot be written: found before the movie is tracked (on a full disk an empty
    # probe file still fits, so that case is not in the list: the table, complete, would rightly stay)
    ("track-json", ["track", "{movie}", "--out", "{out}/t.parquet", "--json", "{D}/t.json"]),
    ("analyze", ["analyze", "{movie}", "--radius", "5e-7", "--viscosity", "1e-3", "--temperature", "293",
                 "--report", "{D}/rep"]),
    ("msd", ["msd", "{table}", "--json", "{D}/m.json", "--plot", "{D}/m.png"]),
    ("velocity", ["velocity", "{table}", "--axes", "xy", "--out", "{D}/v.csv", "--report", "{D}/vr"]),
    ("wall-json", ["wall", "--radius", "1e-6", "--height", "2e-6", "--json", "{D}/w.json"]),
    ("wall-plot", ["wall", "--radius", "1e-6", "--height", "2e-6", "--plot", "{D}/w.png"]),
    ("render", ["render", "{table_ok}", "--out", "{D}/r", "--shape", "32", "32"]),
    # pages that hold the image at every height (smaller ones would add a warning line to the one error line)
    ("render-calibration", ["render-calibration", "--out", "{D}/c", "--z-range", "-2e-6", "2e-6", "--z-step", "1e-6",
                            "--shape", "64", "64"]),
    ("simulate", ["simulate", "{scene_ok}", "--out", "{D}/s", "--quiet"]),
]


def _disk_cases():
    cases = []
    for kind, root in (("disk", "{full}"), ("read-only", "{ro}"), ("unwritable", "/proc/ptrack-fault-suite")):
        for wid, argv in _WRITERS:
            if kind == "disk" and wid == "track-json":
                continue
            cases.append(Case(f"{kind}-{wid}", kind, [a.replace("{D}", root + "/" + wid) for a in argv],
                              needs={"disk": "full", "read-only": "ro"}.get(kind)))
    return cases


def _interrupt_cases():
    return [
        Case("ctrl-c-simulate", "interrupt", ["simulate", "{scene_long}", "--out", "{out}/s", "--quiet"],
             needs="subprocess", exit_code=130),
        Case("ctrl-c-dem", "interrupt", ["simulate", "{dem_long}", "--out", "{out}/s", "--quiet"],
             needs="subprocess", exit_code=130),
    ]


# cases that fail because of a bug in a file helper F does not own (owner's file in the reason)
XFAIL: dict[str, str] = {}

CASES: list[Case] = _movie_cases() + _table_cases() + _scene_cases() + _number_cases() + _disk_cases() \
    + _interrupt_cases()
for _c in CASES:
    _c.xfail = XFAIL.get(_c.id)


# ---------------------------------------------------------------------------------------------------
# running a case


_PROGRESS = re.compile(r"^[^|\n\r]*?\d+%\|[^|\n\r]*\| [^\[\n\r]*\[[^\]\n\r]*\]")


@dataclass
class Outcome:
    code: object
    stderr: str
    stdout: str
    new_paths: list = field(default_factory=list)
    exception: BaseException | None = None
    seconds: float = 0.0

    def lines(self) -> list[str]:
        """Non-empty stderr lines, progress bars (tqdm) and their redraws removed."""
        out = []
        for line in self.stderr.split("\n"):
            line = _PROGRESS.sub("", line.split("\r")[-1]).strip()
            if line:
                out.append(line)
        return out

    def started_work(self) -> bool:
        """A progress bar was drawn: the command began its work."""
        return bool(_PROGRESS.search(self.stderr))

    def problems(self, expected_code: int = 2, not_words=(), expect: str | None = None) -> list[str]:
        p = []
        lines = self.lines()
        if expect and lines and expect not in lines[-1]:
            p.append(f"the message does not name {expect}: {lines[-1]}")
        bad = [w for w in not_words if lines and w in lines[-1].lower()]
        if bad:
            p.append(f"wrong blame ({', '.join(bad)}): {lines[-1]}")
        if self.exception is not None:
            p.append(f"traceback: {type(self.exception).__name__}: {str(self.exception)[:200]}")
        elif self.code != expected_code:
            p.append(f"exit {self.code}, expected {expected_code}")
        if "Traceback" in self.stderr:
            p.append("traceback on stderr")
        if self.exception is None and (len(lines) != 1 or not lines[0].startswith("error: ")):
            p.append(f"stderr is not one 'error:' line: {lines[:4]}")
        if self.new_paths:
            p.append(f"left behind: {[str(x) for x in self.new_paths[:5]]}")
        return p


def _stat(p: Path):
    try:
        st = p.stat()
    except FileNotFoundError:
        return None
    return st.st_size, st.st_mtime_ns


def _snapshot(*dirs) -> set:
    s = set()
    for d in dirs:
        d = Path(d)
        if d.exists():
            s.update(d.rglob("*"))
    return s


def run_inprocess(argv: list[str], cwd: Path, watch=()) -> Outcome:
    """``ptrack.cli.main(argv)`` in ``cwd``, capturing stdout/stderr; exceptions are caught and kept."""
    from ptrack.cli import main

    before = _snapshot(cwd, *watch)
    before_stat = {p: _stat(p) for p in before if p.is_file()}
    err, out = io.StringIO(), io.StringIO()
    old = os.getcwd()
    t0 = time.perf_counter()
    exc = None
    code = None
    os.chdir(cwd)

    def show(message, category, filename, lineno, file=None, line=None):  # as Python prints them, not pytest
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))

    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out), warnings.catch_warnings():
            warnings.resetwarnings()  # Python's own defaults, not pytest's
            warnings.simplefilter("default")
            for cat in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
                warnings.simplefilter("ignore", cat)
            warnings.showwarning = show
            code = main(argv)
    except BaseException as e:  # noqa: BLE001 - a traceback is what the suite looks for
        exc = e
    finally:
        os.chdir(old)
    new = sorted(_snapshot(cwd, *watch) - before)
    new += sorted(f"{p} (changed)" for p, st in before_stat.items() if _stat(p) != st)
    return Outcome(code, err.getvalue(), out.getvalue(), new, exc, time.perf_counter() - t0)


def _wait_for(folder: Path, pattern: str, limit: float, proc) -> None:
    """Wait until a file matching ``pattern`` appears under ``folder`` (the run has begun its work)."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < limit and proc.poll() is None:
        if folder.exists() and any(folder.rglob(pattern)):
            return
        time.sleep(0.05)


def run_interrupted(argv: list[str], cwd: Path, wait_for: str = "*.part", after: float = 0.3,
                    limit: float = 90.0, sig=signal.SIGINT) -> Outcome:
    """Run the CLI in a subprocess, send ``sig`` ``after`` s after ``wait_for`` appears; it must end within ``limit`` s.

    ``limit`` catches a signal that is ignored (the kernels ran on for minutes), not a slow stop: the
    frames done are written out as the table first (a million rows took 15 s at load 16 on 2 cores)."""
    before = _snapshot(cwd)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "ptrack", *argv], cwd=cwd, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=env)
    _wait_for(cwd, wait_for, 30.0, p)
    time.sleep(after)
    exc = None
    if p.poll() is None:
        p.send_signal(sig)
        try:
            out, err = p.communicate(timeout=limit)
        except subprocess.TimeoutExpired:
            p.kill()
            out, err = p.communicate()
            exc = TimeoutError(f"still running {limit:g} s after the signal")
    else:
        out, err = p.communicate()
        exc = RuntimeError(f"ended (exit {p.returncode}) before the signal was sent")
    new = sorted(x for x in _snapshot(cwd) - before if x.suffix == ".part" or (x.is_dir() and not any(x.iterdir())))
    return Outcome(p.returncode, err, out, new, exc, time.perf_counter() - t0)


def kill_and_resume(scene: Path, work: Path, signals) -> dict:
    """A DEM run killed by each of ``signals`` in turn (each after a checkpoint), then resumed to the end.

    Returns the table of an uninterrupted run in another folder ("reference"), the resumed one
    ("resumed", None if unreadable), the exit codes and the wall time.
    """
    from ptrack.table import read_table

    t0 = time.perf_counter()
    ref = work / "reference"
    r = subprocess.run([sys.executable, "-m", "ptrack", "simulate", str(scene), "--out", str(ref), "--quiet"],
                       capture_output=True, text=True)
    codes = [r.returncode]
    out = work / "killed"
    for i, sig in enumerate(signals):
        argv = [sys.executable, "-m", "ptrack", "simulate", str(scene), "--out", str(out), "--quiet"]
        if i:
            argv.append("--resume")
        # each kill after the next checkpoint: the one before, if any, is moved aside to see the new one
        ck = out / "checkpoint.npz"
        mtime = ck.stat().st_mtime_ns if ck.exists() else None
        p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        t1 = time.perf_counter()
        while p.poll() is None and time.perf_counter() - t1 < 60:
            if ck.exists() and ck.stat().st_mtime_ns != mtime:
                break
            time.sleep(0.01)
        if p.poll() is None:
            p.send_signal(sig)  # at once: on an idle machine the rest of the run takes well under a second
        p.communicate(timeout=60)
        codes.append(p.returncode)
        if p.returncode == 0:
            break  # the run ended before the signal landed (a fast machine): the final resume has nothing to do
    # always resumed: after a kill it continues; after a run that finished it is a no-op ("run already complete")
    r = subprocess.run([sys.executable, "-m", "ptrack", "simulate", str(scene), "--out", str(out), "--quiet",
                        "--resume"], capture_output=True, text=True)
    codes.append(r.returncode)
    stderr = r.stderr.strip().splitlines()[-1:] if r.stderr.strip() else []
    res = {"codes": codes, "reference": read_table(ref / "trajectories.parquet"), "resumed": None,
           "stderr": stderr}
    with contextlib.suppress(Exception):
        res["resumed"] = read_table(out / "trajectories.parquet")
    res["seconds"] = time.perf_counter() - t0
    return res


def run_deadline(argv: list[str], cwd: Path, deadline: float) -> Outcome:
    """Run the CLI in a subprocess that must end by itself within ``deadline`` s (else it is killed)."""
    before = _snapshot(cwd)
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "ptrack", *argv], cwd=cwd, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    exc = None
    try:
        out, err = p.communicate(timeout=deadline)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
        exc = TimeoutError(f"still running after {deadline:g} s")
    return Outcome(p.returncode, err, out, sorted(_snapshot(cwd) - before), exc, time.perf_counter() - t0)


def _mount_tmpfs(path: Path, size: str, readonly: bool = False) -> str | None:
    """Mount a tmpfs at ``path``; return None, or why it could not be mounted."""
    path.mkdir(parents=True, exist_ok=True)
    opts = f"size={size}" + (",ro" if readonly else "")
    if shutil.which("mount") is None:
        return "no 'mount' command"
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)], capture_output=True, text=True)
    return None if r.returncode == 0 else f"cannot mount a tmpfs: {r.stderr.strip() or r.returncode}"


def _umount(path: Path) -> None:
    subprocess.run(["umount", str(path)], capture_output=True)


def _fill(path: Path) -> None:
    """Fill the file system at ``path`` to the last byte."""
    for name, block in (("filler", 4096), ("filler2", 1)):
        with contextlib.suppress(OSError), open(path / name, "ab", buffering=0) as fh:
            while True:
                fh.write(b"\0" * block)


class Suite:
    """The corpus and mounts, set up once; ``run(case)`` gives the Outcome."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.corpus = build_corpus(self.root / "corpus")
        self.mounts: dict[str, Path] = {}
        self.mount_errors: dict[str, str] = {}
        try:
            for name, ro in (("full", False), ("ro", True)):
                d = self.root / name
                why = _mount_tmpfs(d, "2m", readonly=ro)
                if why:
                    self.mount_errors[name] = why
                else:
                    self.mounts[name] = d
                    if not ro:
                        _fill(d)
        except BaseException:
            self.close()
            raise

    def start_background(self, cases, kill_resume=True) -> None:
        """Start the subprocess cases (and the kill/resume run) in threads: they mostly wait, so they
        overlap with the in-process cases."""
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(max_workers=4)
        self._jobs = {c.id: self._pool.submit(self._run_now, c) for c in cases
                      if c.needs == "subprocess" or c.deadline is not None}
        if kill_resume:
            work = self.root / "kill_resume"
            work.mkdir(exist_ok=True)
            self._jobs["kill-resume"] = self._pool.submit(
                kill_and_resume, self.corpus["dem"], work, [signal.SIGKILL, signal.SIGKILL])

    def kill_resume(self) -> dict:
        job = self._jobs.get("kill-resume")
        if job is None:
            work = self.root / "kill_resume"
            work.mkdir(exist_ok=True)
            return kill_and_resume(self.corpus["dem"], work, [signal.SIGKILL, signal.SIGKILL])
        return job.result()

    def skip_reason(self, case: Case) -> str | None:
        if case.needs in ("full", "ro") and case.needs not in self.mounts:
            return self.mount_errors.get(case.needs, "no tmpfs")
        return None

    def run(self, case: Case) -> Outcome:
        job = getattr(self, "_jobs", {}).get(case.id)
        return job.result() if job is not None else self._run_now(case)

    def _run_now(self, case: Case) -> Outcome:
        work = self.root / "cases" / case.id.replace("/", "_")
        out = work / "out"  # exists and is empty: what a case writes there is left behind
        out.mkdir(parents=True, exist_ok=True)
        argv = case.resolve(self.corpus, out, self.mounts)
        watch = [self.root / "corpus"] + list(self.mounts.values())
        if case.needs == "subprocess":
            return run_interrupted(argv, work, wait_for="checkpoint.npz" if "dem" in case.id else "*.part")
        if case.deadline is not None:
            return run_deadline(argv, work, case.deadline)
        if case.setup is not None:
            pre = run_inprocess(case.resolve(self.corpus, out, self.mounts, case.setup), work)
            if pre.code != 0 or pre.exception is not None:
                return Outcome(pre.code, pre.stderr, pre.stdout, [], pre.exception or RuntimeError(
                    f"setup {case.setup[:2]} failed: {pre.lines()[-1:] or pre.code}"), pre.seconds)
        return run_inprocess(argv, work, watch)

    def close(self):
        if getattr(self, "_pool", None) is not None:
            self._pool.shutdown(wait=True)
        for d in self.mounts.values():
            _umount(d)


# ---------------------------------------------------------------------------------------------------
# the tests


@pytest.fixture(scope="module")
def suite(tmp_path_factory, request):
    s = Suite(tmp_path_factory.mktemp("faults"))
    chosen = {getattr(item, "callspec", None) and item.callspec.id for item in request.session.items}
    s.start_background([c for c in CASES if c.id in chosen],
                       kill_resume=any("killed" in item.name for item in request.session.items))
    yield s
    s.close()


def _param(c: Case):
    marks = [pytest.mark.xfail(strict=True, reason=c.xfail)] if c.xfail else []
    return pytest.param(c, id=c.id, marks=marks)


@pytest.mark.parametrize("case", [_param(c) for c in CASES])
def test_fault_is_one_clean_line(suite, case):
    why = suite.skip_reason(case)
    if why:
        pytest.skip(why)
    outcome = suite.run(case)
    problems = outcome.problems(case.exit_code, case.not_words, case.expected_text(suite.corpus))
    assert not problems, problems
    if case.kind in ("read-only", "unwritable"):
        assert not outcome.started_work(), "the output was checked only after the work"
    if case.kind == "number":
        opt = next(a for a in case.argv if a.startswith("--") and a in case.id)
        assert opt in outcome.lines()[0], outcome.lines()


def test_every_numeric_option_has_bad_value_cases():
    from ptrack.cli import COMMANDS, STUDIES, command_parser

    covered = {c.id.split("=")[0] for c in CASES if c.kind == "number"}
    for name in [n for n, (m, _) in COMMANDS.items() if m] + [f"study {s}" for s in STUDIES]:
        try:
            _, parser = command_parser(name)
        except Exception:
            continue
        for a in parser.numeric_actions:
            if a.choices:
                continue
            opt = max([s for s in a.option_strings if s.startswith("--")], key=len)
            assert f"{name.replace(' ', '-')}{opt}" in covered, (name, opt)


def test_full_disk_keeps_the_previous_file(suite):
    """An atomic rewrite on a full disk fails cleanly and leaves the old content."""
    if "full" not in suite.mounts:
        pytest.skip(suite.mount_errors.get("full", "no tmpfs"))
    from ptrack.errors import atomic_output, os_error_message

    full = suite.mounts["full"]
    (full / "filler2").unlink(missing_ok=True)  # a few pages for the previous file
    os.truncate(full / "filler", max(0, (full / "filler").stat().st_size - 65536))
    prev = full / "prev.json"
    prev.write_text("{}")
    _fill(full)
    before = sorted(full.rglob("*"))
    with pytest.raises(OSError) as info:
        with atomic_output(prev, "w") as fh:
            fh.write("x" * 100_000)
            fh.flush()
    assert prev.read_text() == "{}"
    assert sorted(full.rglob("*")) == before
    cause, fix = os_error_message(info.value)
    assert cause.startswith("No space left on device") and "space" in fix


def test_dem_killed_twice_then_resumed_gives_every_frame_of_an_uninterrupted_run(suite):
    """SIGKILL after a checkpoint, SIGKILL of the resumed run after the next one, resume: same table."""
    r = suite.kill_resume()
    ref, got = r["reference"], r["resumed"]
    assert r["codes"][0] == 0 and r["codes"][-1] == 0, (r["codes"], r["stderr"])
    # the first kill lands mid-run; the second lands too unless the resumed run finished first (a fast machine:
    # the final --resume then finds the run complete and does nothing; tests/test_resume.py waits for the double
    # kill itself)
    assert r["codes"][1] == -signal.SIGKILL and r["codes"][2] in (-signal.SIGKILL, 0), r["codes"]
    if r["codes"][2] == 0:
        assert r["stderr"] and "run already complete" in r["stderr"][0], r["stderr"]
    assert got is not None, "the resumed table cannot be read"
    assert "incomplete" not in got.attrs["ptrack"]
    assert sorted(got["frame"].unique()) == sorted(ref["frame"].unique())
    cols = ["frame", "particle", "x", "y", "z", "vx", "vy", "vz"]
    assert np.array_equal(got[cols].to_numpy(), ref[cols].to_numpy())


def test_velocity_of_a_flat_z_table_skips_z_with_a_word(suite, tmp_path):
    """z the same in every row: x and y analysed, one note, no numpy warning, exit 0."""
    o = run_inprocess(["velocity", str(suite.corpus["flat_z"]), "--out", str(tmp_path / "v.csv"), "--report",
                       str(tmp_path)], tmp_path)
    assert o.exception is None and o.code == 0, (o.exception, o.stderr)
    assert o.lines() == [], o.lines()  # no RuntimeWarning (overflow in the ensemble weights), no error
    assert "note: z is 2 µm in every row" in o.stdout and "v_z" not in o.stdout
    import pandas as pd

    vel = pd.read_csv(tmp_path / "v.csv", comment="#")
    assert np.isfinite(vel["vx"]).all() and vel["vz"].isna().all()


def test_ensemble_weights_do_not_overflow_for_tiny_errors():
    """Inverse-variance weights of errors ~1e-151 m/s: same mean and error as for errors scaled to 1."""
    import pandas as pd

    from ptrack.motion.velocity import ensemble_velocity

    v = np.array([1.0, 2.0, 4.0])
    e = np.array([1.0, 2.0, 0.5])
    got = []
    for scale in (1.0, 1e-151):
        vel = pd.DataFrame({"vx": v * scale, "vx_err": e * scale})
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            got.append(ensemble_velocity(vel, axes="x", n_boot=0).iloc[0])
    w = 1 / e**2
    assert got[0]["v"] == pytest.approx(np.sum(w * v) / np.sum(w), rel=1e-14)
    assert got[0]["v_err"] == pytest.approx(1 / np.sqrt(np.sum(w)), rel=1e-14)
    assert got[1]["v"] == pytest.approx(got[0]["v"] * 1e-151, rel=1e-14)
    assert got[1]["v_err"] == pytest.approx(got[0]["v_err"] * 1e-151, rel=1e-14)


def test_output_dir_all_or_nothing(tmp_path):
    """A failing command leaves no folder it made (with what it wrote); in a folder that was there, the files
    already written stay."""
    from ptrack.errors import output_dir

    new = tmp_path / "a" / "b"
    with pytest.raises(OSError):
        with output_dir(new, all_or_nothing=True) as d:
            (d / "movie.tif").write_bytes(b"x")
            raise OSError(28, "No space left on device")
    assert list(tmp_path.iterdir()) == []
    old = tmp_path / "old"
    old.mkdir()
    with pytest.raises(OSError):
        with output_dir(old / "sub", all_or_nothing=True):
            raise OSError(28, "No space left on device")
    assert list(tmp_path.iterdir()) == [old] and list(old.iterdir()) == []
    with pytest.raises(OSError):
        with output_dir(old, all_or_nothing=True) as d:
            (d / "movie.tif").write_bytes(b"x")
            raise OSError(28, "No space left on device")
    assert [p.name for p in old.iterdir()] == ["movie.tif"]
