"""Stage drift by phase correlation (ptrack.image.drift) on frames shifted by known sub-pixel amounts."""
import numpy as np
import pandas as pd
import pytest

from ptrack.errors import UserError
from ptrack.image.drift import frame_drift, subtract_frame_drift

SHAPE = (128, 160)


def spectrum(xs, ys, s=1.5, photons=3000.0, shape=SHAPE):
    """Fourier transform of a periodic field of Gaussian spots (px; exact, band-limited)."""
    ky = np.fft.fftfreq(shape[0])
    kx = np.fft.fftfreq(shape[1])
    Ey = np.exp(-2j * np.pi * np.outer(ys, ky))      # n x H
    Ex = np.exp(-2j * np.pi * np.outer(xs, kx))      # n x W
    g = np.exp(-2 * np.pi ** 2 * s ** 2 * (ky[:, None] ** 2 + kx[None, :] ** 2))
    return photons * g * (Ey.T @ Ex)


def fourier_shift(F, dx, dy, shape=SHAPE):
    """Spectrum of the image moved by (dx, dy) px (columns, rows)."""
    ky = np.fft.fftfreq(shape[0])[:, None]
    kx = np.fft.fftfreq(shape[1])[None, :]
    return F * np.exp(-2j * np.pi * (kx * dx + ky * dy))


def movie(n_frames, step_px, rng, n=50, jump_at=None, jump=(6.3, -4.7), n_stuck=0, shape=SHAPE):
    """Frames of n spots moving by Brownian steps of ``step_px`` px rms per axis, the whole field shifted
    by a known stage drift (a sub-pixel random walk plus a linear creep, and optionally a ``jump`` (px) from frame
    ``jump_at`` on), under an illumination fixed to the camera (gradient + vignetting), Poisson photons + read
    noise. ``n_stuck`` more spots are stuck to the coverslip (they move with the stage only).

    Returns (frames, drift (n_frames x 2, px), mean displacement of all particles, the stuck ones at 0
    (n_frames x 2, px))."""
    H, W = shape
    yy, xx = np.mgrid[:H, :W]
    illum = (1 + 0.3 * xx / W) * (1 - 0.3 * ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / (W * W / 2))
    xs, ys = rng.uniform(0, W, n), rng.uniform(0, H, n)
    d = np.cumsum(rng.normal(0, 0.25, (n_frames, 2)), axis=0) + np.linspace(0, 1, n_frames)[:, None] * [2.0, -1.5]
    if jump_at is not None:
        d[jump_at:] += jump
    d -= d[0]
    px, py = xs.copy(), ys.copy()
    stuck = spectrum(rng.uniform(0, W, n_stuck), rng.uniform(0, H, n_stuck), shape=shape) if n_stuck else 0.0
    frames, mean = [], []
    for k in range(n_frames):
        if k:
            px += rng.normal(0, step_px, n)
            py += rng.normal(0, step_px, n)
        mean.append([np.sum(px - xs) / (n + n_stuck), np.sum(py - ys) / (n + n_stuck)])
        img = np.real(np.fft.ifft2(fourier_shift(spectrum(px, py, shape=shape) + stuck, d[k, 0], d[k, 1], shape=shape)))
        lam = np.clip((img + 30.0) * illum, 0, None)
        frames.append((rng.poisson(lam) + 100 + 1.5 * rng.normal(size=shape)).astype(np.float32))
    return frames, d, np.array(mean)


def test_static_scene_known_subpixel_shifts_and_a_jump():
    """A static sample: every frame is frame 0 moved by a known sub-pixel drift (and a 7.8 px jump that
    linking with a few px search range would not follow). RMS error per axis < 0.02 px (measured 0.013, mostly
    the border taper: 0.0006 px on clean periodic frames), metres = px x pixel size."""
    rng = np.random.default_rng(3)
    frames, d, _ = movie(30, 0.0, rng, jump_at=17)
    tab = frame_drift(iter(frames), pixel_size=1e-7, frame_interval=0.05)
    est = tab[["x_px", "y_px"]].to_numpy()
    err = est - d
    assert np.sqrt(np.mean(err ** 2)) < 0.02, np.sqrt(np.mean(err ** 2))
    assert np.abs(err).max() < 0.05, np.abs(err).max()
    assert np.allclose(tab[["x", "y"]].to_numpy(), est * 1e-7)
    assert list(tab["frame"]) == list(range(30))
    assert np.allclose(tab["t"], np.arange(30) * 0.05)
    assert tab["error"].iloc[0] == 0 and (tab["error"] < 0.5).all()
    # against frame 0 alone: the same on a static scene
    est0 = frame_drift(frames, pixel_size=1e-7, reference="first")[["x_px", "y_px"]].to_numpy()
    assert np.sqrt(np.mean((est0 - d) ** 2)) < 0.02


def test_moving_particles_running_reference():
    """Particles diffusing 0.4 px per frame per axis (4 px rms over the movie, more than their size):
    what the images measure is the drift plus the particles' mean displacement; the running reference
    follows it within 0.15 px RMS over 40 frames (measured 0.116; the error grows as a random walk of the
    per-frame registration errors), registering against frame 0 alone does worse (measured 0.22)."""
    rng = np.random.default_rng(4)
    frames, d, mean = movie(40, 0.4, rng)
    est = frame_drift(frames, pixel_size=1e-7)[["x_px", "y_px"]].to_numpy()
    est0 = frame_drift(frames, pixel_size=1e-7, reference="first")[["x_px", "y_px"]].to_numpy()
    rms = np.sqrt(np.mean((est - d - mean) ** 2))
    rms0 = np.sqrt(np.mean((est0 - d - mean) ** 2))
    assert rms < 0.15, rms
    assert rms0 > 1.5 * rms, (rms0, rms)


def test_subtract_frame_drift_restores_stage_coordinates():
    rng = np.random.default_rng(5)
    n_fr, n_p, px = 12, 4, 2e-7
    d = np.c_[np.arange(n_fr) * 0.3, -np.arange(n_fr) * 0.2]
    tab = pd.DataFrame({"frame": np.arange(n_fr), "x": d[:, 0] * px, "y": d[:, 1] * px,
                        "x_px": d[:, 0], "y_px": d[:, 1]})
    true = rng.uniform(0, 100, (n_p, n_fr, 2))
    fr = np.tile(np.arange(n_fr), n_p)
    obs = true.reshape(-1, 2) + d[fr]
    df = pd.DataFrame({"frame": fr, "particle": np.repeat(np.arange(n_p), n_fr), "x": obs[:, 0] * px,
                       "y": obs[:, 1] * px, "x_px": obs[:, 0], "y_px": obs[:, 1]})
    out = subtract_frame_drift(df, tab)
    assert np.allclose(out[["x_px", "y_px"]].to_numpy(), true.reshape(-1, 2))
    assert np.allclose(out[["x", "y"]].to_numpy(), true.reshape(-1, 2) * px)
    assert np.allclose(df[["x_px", "y_px"]].to_numpy(), obs)     # the input is not modified
    feats = df[["frame", "x_px", "y_px"]]
    assert np.allclose(subtract_frame_drift(feats, tab)[["x_px", "y_px"]].to_numpy(), true.reshape(-1, 2))


@pytest.mark.parametrize("bad", [
    dict(frames=[], pixel_size=1e-7),
    dict(frames=[np.zeros((8, 8)), np.zeros((8, 9))], pixel_size=1e-7),
    dict(frames=[np.zeros((2, 8, 8))], pixel_size=1e-7),
    dict(frames=[np.zeros((8, 8))], pixel_size=0.0),
    dict(frames=[np.zeros((8, 8))], pixel_size=1e-7, reference="last"),
    dict(frames=[np.zeros((8, 8))], pixel_size=1e-7, bandpass=(5, 2)),
])
def test_bad_input_is_a_user_error(bad):
    with pytest.raises(UserError):
        frame_drift(**bad)


def test_track_stage_drift_keeps_tracks_across_a_stage_jump(tmp_path):
    """`ptrack track --stage-drift`: a 15 px stage jump breaks every track without it, and none with it."""
    import json
    import warnings

    import tifffile

    from ptrack.cli import main
    from ptrack.table import read_table

    rng = np.random.default_rng(11)
    frames, d, _ = movie(30, 0.3, rng, n=30, jump_at=15, jump=(15.0, -9.0))
    tifffile.imwrite(tmp_path / "m.tif", np.clip(np.round(np.stack(frames)), 0, 65535).astype(np.uint16), imagej=True,
                     metadata={"axes": "TYX"})
    longest = {}
    for name, extra in (("plain", []), ("drift", ["--stage-drift"])):
        out, js = tmp_path / f"{name}.parquet", tmp_path / f"{name}.json"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert main(["track", str(tmp_path / "m.tif"), "--pixel-size", "1e-7", "--frame-interval", "0.1",
                         "--search-range", "3", "--out", str(out), "--json", str(js), *extra]) == 0
        t = read_table(out)
        longest[name] = int(t.groupby("particle").size().max())
        s = json.loads(js.read_text())
        if name == "drift":
            assert "stage_drift" in s["stage_times_s"]
            assert abs(s["stage_drift_max_px"] - float(np.hypot(*d.T).max())) < 1.0
            # positions are in stage coordinates: a particle's track has no jump at frame 15
            g = t.sort_values("frame").groupby("particle")
            steps = np.concatenate([np.hypot(np.diff(p["x_px"]), np.diff(p["y_px"])) for _, p in g])
            assert steps.max() < 3.0
    assert longest["plain"] <= 15 and longest["drift"] == 30, longest


def test_no_unique_peak_is_unreliable_and_track_refuses(tmp_path):
    """Sparse particles stepping farther than their size leave no correlation peak: the frames are marked
    unreliable (drift interpolated, kept out of the reference) and `track --stage-drift` refuses, writing nothing."""
    import tifffile

    from ptrack.cli import main

    rng = np.random.default_rng(5)
    frames, d, _ = movie(20, 5.0, rng, n=8)           # 8 spots, 5 px rms steps, no stage jump
    r = frame_drift(frames, 1e-7)
    assert r["reliable"].iloc[0] and (~r["reliable"]).mean() > 0.8
    # what is kept is an interpolation between reliable frames, not a noise peak tens of px away
    assert np.abs(r[["x_px", "y_px"]].to_numpy()).max() < 10
    good = frame_drift(movie(20, 0.3, np.random.default_rng(6), n=50)[0], 1e-7)
    assert good["reliable"].all() and (good["peak_ratio"].iloc[1:] > 2).all()
    tifffile.imwrite(tmp_path / "m.tif", np.clip(np.round(np.stack(frames)), 0, 65535).astype(np.uint16),
                     imagej=True, metadata={"axes": "TYX"})
    out = tmp_path / "t.parquet"
    assert main(["track", str(tmp_path / "m.tif"), "--pixel-size", "1e-7", "--frame-interval", "0.1",
                 "--stage-drift", "--out", str(out)]) == 2
    assert not out.exists()
