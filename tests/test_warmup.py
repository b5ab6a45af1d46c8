"""`ptrack warmup`: every shipped scene cut to a few particles and steps, run to fill numba's cache."""
import tomllib

import pandas as pd

from ptrack.cli import main
from ptrack.commands.warmup import N_PARTICLES, shipped_scenes, short_scene


def test_every_shipped_scene_is_cut_short_and_really_steps(tmp_path):
    from sim.run import run_scene

    paths = shipped_scenes()
    assert len(paths) >= 5  # the shipped scenes are found (source tree or package data)
    for path in paths:
        with open(path, "rb") as fh:
            raw = tomllib.load(fh)
        scene = short_scene(raw)
        assert scene.particles.count <= N_PARTICLES
        assert scene.time.output_interval == scene.time.final
        res = run_scene(scene, tmp_path / path.stem, progress=False)
        tab = pd.read_parquet(res.trajectories, columns=["frame", "t"])
        # frame 0 and the final frame: the steppers ran (a cache filled by a run of zero steps is not warm)
        assert tab["frame"].nunique() == 2 and tab["t"].max() > 0, path.name


def test_warmup_command_exits_0(capsys):
    assert main(["warmup", "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_warmup_compiles_the_gdpt_kernels():
    # a fresh process (this one may have compiled them already): warm_gdpt finds its two particles, and a
    # crowded frame after it (overlapping pairs, so the split and flip passes run) needs no kernel of the
    # GDPT modules that warm_gdpt did not already compile or load (numba cache=True keeps them on disk)
    import subprocess
    import sys

    code = """
import importlib, numba, numpy as np
from ptrack.commands.warmup import warm_gdpt
from ptrack.calibration import build_calibration, locate_frame_3d
mods = [importlib.import_module("ptrack.calibration")] + [importlib.import_module("ptrack.gdpt." + m)
        for m in ("ncc", "fast", "interp", "build", "stack", "heights", "field")]
def sigs():
    return {(m.__name__, k): len(v.signatures) for m in mods for k, v in vars(m).items()
            if isinstance(v, numba.core.registry.CPUDispatcher)}
assert not any(sigs().values())
found = warm_gdpt()
warm = sigs()
rng = np.random.default_rng(1)
yy, xx = np.mgrid[0:128, 0:128].astype(float)
def frame(spots):
    img = np.full((128, 128), 100.0)
    for x, y, z in spots:
        sx, sy = 1.5 * np.hypot(1.0, (z - 0.5) / 0.6), 1.5 * np.hypot(1.0, (z + 0.5) / 0.6)
        img += 4e4 / (2 * np.pi * sx * sy) * np.exp(-0.5 * (((xx - x) / sx) ** 2 + ((yy - y) / sy) ** 2))
    return rng.poisson(img).astype(np.float32)
z = np.linspace(-2.0, 2.0, 9)
cal = build_calibration(np.stack([frame([(63.5, 64.0, zk)]) for zk in z]), z * 1e-6, 1e-7)
spots = [(20 + 25 * (k % 4) + rng.uniform(-3, 3), 20 + 25 * (k // 4) + rng.uniform(-3, 3), rng.uniform(-1.8, 1.8))
         for k in range(16)]
spots += [(x + 3.0, y + 1.5, rng.uniform(-1.8, 1.8)) for x, y, _ in spots[:5]]
n = len(locate_frame_3d(frame(spots), cal))
new = sorted(k[1] for k, v in sigs().items() if v > warm[k])
print(found, sum(v > 0 for v in warm.values()), n, ",".join(new) or "-")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "2" and int(out[1]) >= 2, out       # found both; its kernels compiled
    assert int(out[2]) >= 16, out                       # the crowded frame is really tracked
    assert out[3] == "-", f"kernels the warm-up leaves to a user's first 3D run: {out[3]}"


def test_warmup_links_with_the_numba_linker():
    # two points moving < 1 px between two frames: two trajectories, and the linker kernel compiled
    from ptrack import linknb
    from ptrack.commands.warmup import warm_link

    assert warm_link() == 2
    assert linknb._link_all.signatures


def test_warmup_compiles_the_image_kernels_ptrack_track_uses():
    # a fresh process: tracking the warm-up's small movies (fluorescence spots with overlapping and unresolved
    # pairs, dark particles on an uneven field, rings; 16 and 8 bits) compiles the detector, the isolated,
    # joint and split fits and the radial-profile centres, so a user's first `ptrack track` loads them
    import subprocess
    import sys

    code = ("from ptrack.commands.warmup import warm_track\n"
            "from ptrack.image import detect, fit, radial\n"
            "from ptrack.image import rings\n"
            "ks = (fit._fit_all, fit._fit_tasks, fit._split_spots, detect._best_over_scales, radial._profile_all)\n"
            "assert not any(k.signatures for k in ks)\n"
            "n = warm_track()\n"
            "print(n, *[len(k.signatures) for k in ks])\n"
            "print(sorted({str(s[0]) for s in rings._patch_dips.signatures}))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.splitlines()
    counts = [int(v) for v in out[0].split()]
    assert counts[0] > 100 and all(c >= 1 for c in counts[1:]), out
    assert "uint8" in out[1] and "uint16" in out[1], out   # the ring test reads raw frames of both camera depths


def test_warmup_compiles_the_analysis_kernels():
    # a fresh process: the synthetic table's analysis compiles the MSD / CVE sums and the velocity kernels
    import subprocess
    import sys

    code = ("from ptrack.commands.warmup import warm_analysis\n"
            "from ptrack.motion import cve, msd, velocity\n"
            "ks = (msd.msd_sums_ragged, cve.cve_sums_ragged, velocity._velocity_kernel, velocity._contact_index)\n"
            "assert not any(k.signatures for k in ks)\n"
            "print(warm_analysis(), *[len(k.signatures) for k in ks])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "320" and all(int(c) >= 1 for c in out[1:]), out
