"""The plots people read (issue 13's findings), checked on the returned figures, not by eye alone:
tracks.png fills its figure with a µm scale bar and tells neighbouring tracks apart, msd.png draws the reported
D over the fitted lags and marks them, D_per_particle.png has each track's error bar. (`make gallery` writes
every figure into one folder to judge them by eye.)"""
import numpy as np
import pytest
from matplotlib.colors import to_hex

from ptrack.motion import brownian_tracks, estimate_diffusion, particle_diffusion
from ptrack.plot import plot_D_per_particle, plot_msd, plot_tracks
from ptrack.table import make_table

D_TRUE, DT, PX = 0.5e-12, 0.1, 1e-7


@pytest.fixture(scope="module")
def tracks():
    xy = brownian_tracks(12, 60, D_TRUE, DT, n_dims=2, seed=3)          # (particle, frame, axis), m
    n, T, _ = xy.shape
    fr = np.tile(np.arange(T), n)
    x = xy[:, :, 0].ravel() + np.repeat(np.linspace(2e-6, 18e-6, n), T)
    y = xy[:, :, 1].ravel() + 6e-6
    df = make_table(fr, fr * DT, np.repeat(np.arange(n), T), x, y, meta={"pixel_size": PX, "frame_interval": DT},
                    x_px=x / PX, y_px=y / PX)
    return df


def test_tracks_png_fills_the_figure_has_a_um_scale_bar_and_distinct_neighbour_colours(tracks):
    img = np.random.default_rng(0).normal(100, 5, (120, 200))
    fig = plot_tracks(img, tracks)                                     # pixel size from the table's metadata
    ax = fig.axes[0]
    assert np.allclose(ax.get_position().bounds, (0, 0, 1, 1))        # no white strip under the image
    bar = [t.get_text() for t in ax.texts if t.get_text().endswith("µm")]
    assert len(bar) == 1 and float(bar[0].split()[0]) > 0             # a scale bar in µm
    lc = ax.collections[0]
    colours = {to_hex(c) for c in lc.get_colors()}
    assert len(colours) >= 10                                          # 12 tracks, not one colour
    # without a pixel size there is no bar (nothing is invented)
    t2 = tracks.copy()
    t2.attrs = {}
    assert not [t for t in plot_tracks(img, t2).axes[0].texts if t.get_text().endswith("µm")]


def test_msd_png_draws_the_reported_D_over_the_fitted_lags(tracks):
    res = estimate_diffusion(tracks, axes=("xy",), motion_blur=0.0, n_boot=20, seed=1)
    D_fit = res.D["xy"]
    fig = plot_msd(res, reported={"xy": (1.1 * D_fit, 0.01 * D_fit, "linking-free")})
    ax = fig.axes[0]
    labels = [ln.get_label() for ln in ax.get_lines()]
    fit = [lab for lab in labels if lab.startswith("fit xy: D = ")]
    assert fit and f"{D_fit * 1e12:.4g}" in fit[0] and "fitted lags" in fit[0]
    assert any(lab.startswith("reported xy (linking-free)") for lab in labels)
    # the fitted lags are drawn filled and the solid fit line ends at the last fitted lag
    f = res.fit["xy"]
    solid = [ln for ln in ax.get_lines() if ln.get_label().startswith("fit xy")][0]
    assert solid.get_xdata().max() <= f["t_max"] * (1 + 1e-9)
    filled = [ln for ln in ax.get_lines() if ln.get_marker() == "o" and ln.get_markerfacecolor() != "none"]
    assert filled and filled[0].get_xdata().max() <= f["t_max"] * (1 + 1e-9)


def test_D_per_particle_png_has_each_tracks_error_bar(tracks):
    per = particle_diffusion(tracks, axes=("xy",), motion_blur=0.0)
    fig = plot_D_per_particle(per, "xy", D_ensemble=D_TRUE, D_stokes_einstein=D_TRUE)
    ax = fig.axes[0]
    assert len(ax.containers) == 1
    cont = ax.containers[0]
    assert cont.has_yerr
    n = int(np.isfinite(per["D_xy"]).sum())
    assert len(cont.lines[0].get_xdata()) == n
    # sorted by D, in µm²/s
    y = cont.lines[0].get_ydata()
    assert np.all(np.diff(y) >= 0) and "µm²/s" in ax.get_ylabel()
