"""Movie reading: formats, calibration metadata with units, bounded memory, clear errors."""
import subprocess
import sys
import tracemalloc

import numpy as np
import pytest
import tifffile

from ptrack.errors import UserError
from ptrack.io import check_not_blank, open_movie, parse_length, parse_time


@pytest.fixture
def stack():
    rng = np.random.default_rng(0)
    return (rng.random((6, 24, 30)) * 4000).astype(np.uint16)


def test_units():
    assert parse_length(0.103, "micron") == pytest.approx(1.03e-7)
    assert parse_length(103, "nm") == pytest.approx(1.03e-7)
    assert parse_length(1.03e-4, "mm") == pytest.approx(1.03e-7)
    assert parse_length(0.103, "\\u00B5m") == pytest.approx(1.03e-7)
    assert parse_length(1, "pixel") is None
    assert parse_time(50, "ms") == pytest.approx(0.05)
    assert parse_time(0.1, "sec") == pytest.approx(0.1)
    assert parse_time(1, "parsec") is None


def test_imagej_metadata_and_memmap(tmp_path, stack):
    p = tmp_path / "ij.tif"
    tifffile.imwrite(p, stack, imagej=True, resolution=(1 / 0.103, 1 / 0.103),
                     metadata={"unit": "um", "finterval": 0.1, "axes": "TYX"})
    with open_movie(p) as m:
        assert (len(m), m.shape, m.dtype) == (6, (24, 30), np.uint16)
        assert m.pixel_size == pytest.approx(1.03e-7)
        assert m.frame_interval == pytest.approx(0.1)
        assert m.memmapped
        np.testing.assert_array_equal(m[4], stack[4])
        np.testing.assert_array_equal(m[-1], stack[-1])
        with pytest.raises(IndexError):
            m[6]
    with open_movie(p, pixel_size=2e-7, frame_interval=0.05) as m:   # flags override metadata
        assert (m.pixel_size, m.frame_interval) == (2e-7, 0.05)


def test_ome_units_and_compressed_pages(tmp_path, stack):
    p = tmp_path / "m.ome.tif"
    tifffile.imwrite(p, stack, compression="zlib", metadata={
        "axes": "TYX", "PhysicalSizeX": 103, "PhysicalSizeXUnit": "nm", "TimeIncrement": 50, "TimeIncrementUnit": "ms"})
    with open_movie(p) as m:
        assert not m.memmapped
        assert m.pixel_size == pytest.approx(1.03e-7)
        assert m.frame_interval == pytest.approx(0.05)
        np.testing.assert_array_equal(np.stack(list(m)), stack)


def test_image_sequences(tmp_path, stack):
    import cv2

    d = tmp_path / "seq"
    d.mkdir()
    for i, f in enumerate(stack):       # natural order: frame_2 before frame_10
        cv2.imwrite(str(d / f"frame_{i * 5}.png"), f)
    with open_movie(d) as m:
        assert len(m) == 6 and m.dtype == np.uint16 and m.pixel_size is None
        np.testing.assert_array_equal(m[2], stack[2])
        with pytest.raises(UserError, match="--pixel-size"):
            m.require_calibration()
    for i, f in enumerate(stack):
        tifffile.imwrite(tmp_path / f"t{i:02d}.tif", f)
    with open_movie(str(tmp_path / "t*.tif"), frame_interval=0.1) as m:
        assert len(m) == 6
        np.testing.assert_array_equal(m[5], stack[5])
        m.pixel_size = 1e-7
        m.require_calibration()


def test_bounded_memory(tmp_path):
    """Iterating a 40 MB movie must not load it: memory-mapped, one frame at a time."""
    p = tmp_path / "big.tif"
    frames = np.zeros((40, 512, 1024), np.uint16)
    frames[:, ::7, ::5] = 1000
    tifffile.imwrite(p, frames)
    del frames
    tracemalloc.start()
    with open_movie(p) as m:
        total = 0
        for f in m:
            total += int(f[0, 0]) + int(f.sum() > 0)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert total == 40 * 1001
    assert peak < 8e6


@pytest.mark.parametrize("kind", ["truncated_contiguous", "truncated_compressed", "junk", "float", "rgb", "channels"])
def test_bad_files_are_clear_errors(tmp_path, stack, kind):
    p = tmp_path / f"{kind}.tif"
    if kind.startswith("truncated"):
        full = tmp_path / "full.tif"
        tifffile.imwrite(full, stack, compression="zlib" if "compressed" in kind else None)
        data = full.read_bytes()
        p.write_bytes(data[: len(data) * 2 // 3])
        match = "truncated|corrupt"
    elif kind == "junk":
        p.write_bytes(b"II*\x00" + b"\xff" * 50)
        match = "corrupt|cannot read"
    elif kind == "float":
        tifffile.imwrite(p, stack.astype(np.float32))
        match = "floating-point"
    elif kind == "rgb":
        tifffile.imwrite(p, np.zeros((20, 20, 3), np.uint8), photometric="rgb")
        match = "RGB"
    else:
        tifffile.imwrite(p, np.zeros((3, 2, 20, 20), np.uint16), imagej=True, metadata={"axes": "TCYX"})
        match = "channels"
    with pytest.raises(UserError, match=match):
        with open_movie(p) as m:
            for _ in m:
                pass


def test_blank_movie(tmp_path):
    p = tmp_path / "dark.tif"
    tifffile.imwrite(p, np.full((5, 16, 16), 100, np.uint16))
    with open_movie(p) as m, pytest.raises(UserError, match="blank"):
        check_not_blank(m)


def test_cli_truncated_and_dark_movies_exit_2_without_output(tmp_path, stack):
    full = tmp_path / "full.tif"
    tifffile.imwrite(full, stack, imagej=True, resolution=(1 / 0.1, 1 / 0.1), metadata={"unit": "um", "finterval": 0.1})
    bad = tmp_path / "bad.tif"
    bad.write_bytes(full.read_bytes()[:3000])
    dark = tmp_path / "dark.tif"
    tifffile.imwrite(dark, np.zeros((5, 16, 16), np.uint16), imagej=True, resolution=(10, 10),
                     metadata={"unit": "um", "finterval": 0.1})
    for movie in (bad, dark):
        out = tmp_path / f"{movie.stem}.parquet"
        r = subprocess.run([sys.executable, "-m", "ptrack", "track", str(movie), "--out", str(out)],
                           capture_output=True, text=True)
        assert r.returncode == 2, r.stderr
        assert r.stderr.startswith("error:") and "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
        assert not out.exists()
        assert not list(tmp_path.glob(f".{out.name}*"))


def test_trackpy_table_round_trip_and_features_to_si_table():
    """trackpy's x, y are pixels: from_trackpy scales them to metres (not read as metres), to_trackpy
    goes back; to_trajectories is the public features (px) -> SI table step of ptrack track."""
    import pandas as pd

    from ptrack.link import from_trackpy, to_trackpy, to_trajectories
    from ptrack.table import metadata

    rng = np.random.default_rng(0)
    f = pd.DataFrame({"frame": np.tile(np.arange(20), 3), "particle": np.repeat([7, 3, 9], 20),
                      "x": rng.uniform(0, 100, 60), "y": rng.uniform(0, 100, 60), "mass": rng.uniform(1, 2, 60)})
    t = from_trackpy(f, 1.5e-7, 0.05)
    assert np.allclose(t["x"], t["x_px"] * 1.5e-7) and t["x"].max() < 2e-5
    assert np.allclose(t["t"], t["frame"] * 0.05) and sorted(t["particle"].unique()) == [0, 1, 2]
    assert metadata(t)["pixel_size"] == 1.5e-7
    back = to_trackpy(t)
    a = back.sort_values(["frame", "mass"]).reset_index(drop=True)
    b = f.sort_values(["frame", "mass"]).reset_index(drop=True)
    assert len(a) == 60 and np.allclose(a[["x", "y"]], b[["x", "y"]], rtol=1e-12)
    feats = f.rename(columns={"x": "x_px", "y": "y_px"}).assign(sigma_x_px=0.1, sigma_y_px=0.2)
    tt = to_trajectories(feats, 2e-7, 0.1)
    assert np.allclose(tt["sigma_y"], 0.2 * 2e-7) and np.isnan(tt["z"]).all()
    with pytest.raises(UserError):
        to_trajectories(feats.drop(columns="particle"), 2e-7, 0.1)
    with pytest.raises(UserError):
        from_trackpy(f, -1.0, 0.1)


def test_hyperstacks_read_by_their_axes(tmp_path):
    """TZYX / TCYX: frames along T, the plane or channel by option; ambiguous stacks refused; a plain
    ImageJ Z stack is a time series; tiny ImageJ pages are not called corrupt."""
    rng = np.random.default_rng(0)
    a = rng.integers(0, 1000, (4, 3, 16, 16)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "tzyx.tif", a, imagej=True, metadata={"axes": "TZYX"})
    tifffile.imwrite(tmp_path / "tcyx.tif", a[:, :2], imagej=True, metadata={"axes": "TCYX"})
    tifffile.imwrite(tmp_path / "zyx.tif", a[0], imagej=True, metadata={"axes": "ZYX"})
    with pytest.raises(UserError, match="--plane"):
        open_movie(tmp_path / "tzyx.tif")
    with open_movie(tmp_path / "tzyx.tif", plane=2) as m:
        assert len(m) == 4 and all((m[i] == a[i, 2]).all() for i in range(4))
    with pytest.raises(UserError, match="--channel"):
        open_movie(tmp_path / "tcyx.tif")
    with open_movie(tmp_path / "tcyx.tif", channel=1) as m:
        assert len(m) == 4 and (m[3] == a[3, 1]).all()
    with pytest.raises(UserError, match="outside"):
        open_movie(tmp_path / "tcyx.tif", channel=2)
    with open_movie(tmp_path / "zyx.tif") as m:
        assert len(m) == 3 and (m[1] == a[0, 1]).all()
    tifffile.imwrite(tmp_path / "tiny.tif", np.ones((5, 1, 1), np.uint16), imagej=True, metadata={"axes": "TYX"})
    with open_movie(tmp_path / "tiny.tif") as m:         # tifffile cannot place the pages; the file is fine
        assert m.shape[0] * m.shape[1] * len(m) == 5
