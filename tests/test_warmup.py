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
    # a fresh process (this one may have compiled them already): warm_gdpt finds its two particles and leaves
    # both correlation kernels compiled (numba cache=True keeps them on disk for the next process)
    import subprocess
    import sys

    code = ("from ptrack.commands.warmup import warm_gdpt\n"
            "from ptrack.gdpt import ncc\n"
            "assert not ncc._ncc_direct.signatures and not ncc._ncc_pages.signatures\n"
            "print(warm_gdpt(), len(ncc._ncc_direct.signatures), len(ncc._ncc_pages.signatures))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "2" and int(out[1]) >= 1 and int(out[2]) >= 1


def test_warmup_links_with_the_numba_linker():
    # two points moving < 1 px between two frames: two trajectories, and the linker kernel compiled
    from ptrack import linknb
    from ptrack.commands.warmup import warm_link

    assert warm_link() == 2
    assert linknb._link_all.signatures
