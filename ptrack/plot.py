"""Figures of the analysis: each takes ``ax=`` (or makes its own figure), returns the figure, and leaves the backend alone.

Figures are built as :class:`matplotlib.figure.Figure` objects, not through
pyplot, so a notebook's figures and backend are untouched and a script needs
no ``matplotlib.use``. Pass ``path`` to also write a PNG (atomically).

Examples
--------
>>> from ptrack.motion import brownian_field, estimate_diffusion
>>> from ptrack.plot import plot_msd
>>> res = estimate_diffusion(brownian_field(40, 30e-6, 0.05e12, 1e-12, 0.1, seed=0), axes="xy", motion_blur=0)
>>> fig = plot_msd(res)
>>> fig.axes[0].get_xlabel()
'lag time t (s)'
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from .errors import atomic_output

UM = 1e6      # m -> µm
UM2 = 1e12    # m^2 -> µm^2


def new_figure(figsize=(6, 4.5), dpi=120, **subplots):
    """(figure, axes) without pyplot: no backend switch, no global figure list."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi)
    return fig, fig.subplots(**subplots)


def save_figure(fig, path, dpi=None) -> Path:
    """Write ``fig`` as a PNG at ``path``, atomically (a failure leaves no half-written file)."""
    path = Path(path)
    with atomic_output(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=dpi)
    return path


def _axes(ax, **kw):
    if ax is None:
        return new_figure(**kw)
    return ax.figure, ax


def plot_msd(result, path=None, title: str | None = None, ax=None, reported: dict | None = None):
    """Log-log ensemble MSD per axis, the fitted model over the lags that were fitted (marked), and the reported D.

    Parameters
    ----------
    result : DiffusionResult or DataFrame
        :func:`ptrack.motion.estimate_diffusion` result (MSD and fit drawn) or
        an :func:`ptrack.motion.ensemble_msd` table.
    path : path-like, optional
        Also write a PNG here.
    title : str, optional
    ax : matplotlib Axes, optional
    reported : dict axis -> (D, D_err, label), optional
        A D reported instead of the fit's (e.g. the linking-free estimate):
        drawn as ``offset + 2 n D t`` with the fit's offset.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, ax = _axes(ax)
    if hasattr(result, "msd") and hasattr(result, "fit"):
        msd, fit, errs = result.msd, result.fit, result.D_err
    else:
        msd, fit, errs = result, {}, {}
    t = msd["t"].to_numpy()
    # about 40 log-spaced lags drawn: on a log axis every lag of a long curve would merge into a thick line
    shown = np.zeros(len(t), bool)
    shown[np.unique(np.round(np.geomspace(1, max(len(t), 1), 40)).astype(int) - 1)] = True
    for i, col in enumerate(c for c in msd.columns if c.startswith("msd_")):
        a = col[4:]
        y = msd[col].to_numpy()
        good = np.isfinite(y) & (y > 0)
        color = f"C{i}"
        se = msd[f"se_{a}"].to_numpy() if f"se_{a}" in msd.columns else np.full(len(y), np.nan)
        f = fit.get(a)
        infit = np.zeros(len(t), bool)
        if f is not None:
            t0 = f.get("t_min") or t[0]
            t1 = f.get("t_max") or t[-1]
            infit = (t >= t0 * (1 - 1e-9)) & (t <= t1 * (1 + 1e-9))
        good = good & (shown | infit)
        ax.errorbar(t[good], y[good] * UM2, yerr=np.nan_to_num(se[good]) * UM2, fmt="none", ecolor=color,
                    elinewidth=0.6, alpha=0.6)
        ax.plot(t[good & ~infit], y[good & ~infit] * UM2, "o", ms=3, mfc="none", color=color, mew=0.8,
                label=f"MSD {a} (± SE); filled: lags fitted")
        if f is not None:
            ax.plot(t[good & infit], y[good & infit] * UM2, "o", ms=5, color=color)
            D = f["slope"] / (2 * f["n_dims"])
            tt = np.geomspace(t[0], t[-1], 100)
            model = f["offset"] + f["slope"] * tt
            err = errs.get(a, np.nan)
            lab = f"fit {a}: D = {D * UM2:.4g}" + (f" ± {err * UM2:.2g}" if np.isfinite(err) else "") + " µm²/s"
            fitted = (tt <= t1 * (1 + 1e-9)) & (model > 0)
            ax.plot(tt[fitted], model[fitted] * UM2, "-", color=color, lw=1.6, label=lab + " (solid: fitted lags)")
            ax.plot(tt[~fitted & (model > 0)], model[~fitted & (model > 0)] * UM2, ":", color=color, lw=1)
            if reported and a in reported:
                Dr, er, name = reported[a]
                if abs(Dr / D - 1) > 1e-9:
                    mr = f["offset"] + 2 * f["n_dims"] * Dr * tt
                    ax.plot(tt[mr > 0], mr[mr > 0] * UM2, "--", color=color, lw=1,
                            label=f"reported {a} ({name}): D = {Dr * UM2:.4g} ± {er * UM2:.2g} µm²/s")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("lag time t (s)")
    ax.set_ylabel("MSD (µm²)")
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    if path is not None:
        save_figure(fig, path)
    return fig


def _scale_bar_um(width_um: float) -> float:
    """A round scale-bar length near a fifth of the width (µm)."""
    target = width_um / 5
    p = 10 ** np.floor(np.log10(target))
    return float(max(m * p for m in (1, 2, 5) if m * p <= target))


def plot_tracks(image, table: pd.DataFrame, path=None, frame: int = 0, pixel_size: float | None = None, ax=None,
                title: str | None = None):
    """One frame with its detections (circles) and every trajectory, each track its own colour; µm scale bar.

    Parameters
    ----------
    image : ndarray (ny, nx)
        The frame shown.
    table : DataFrame
        Trajectories with ``x_px``, ``y_px``, ``frame``, ``particle``.
    path : path-like, optional
        Also write a PNG here.
    frame : int
        Frame of ``image`` (its detections are circled).
    pixel_size : float, optional
        m per px (default from the table's metadata): draws a scale bar.
    ax : matplotlib Axes, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.collections import LineCollection

    img = np.asarray(image, float)
    ny, nx = img.shape
    if ax is None:
        w = 7.0
        fig, ax = new_figure(figsize=(w, w * ny / max(nx, 1)), dpi=110)
        ax.set_position([0, 0, 1, 1])      # the image fills the figure: no white strip
    else:
        fig = ax.figure
    lo, hi = np.percentile(img, [1, 99.8])
    ax.imshow(img, cmap="gray", vmin=lo, vmax=hi if hi > lo else lo + 1, interpolation="nearest")
    srt = table.sort_values(["particle", "frame"], kind="stable")
    part = srt["particle"].to_numpy()
    x, y = srt["x_px"].to_numpy(float), srt["y_px"].to_numpy(float)
    same = (part[1:] == part[:-1]) & np.isfinite(x[1:]) & np.isfinite(x[:-1])
    segs = np.stack([np.c_[x[:-1], y[:-1]], np.c_[x[1:], y[1:]]], axis=1)[same]
    # neighbouring ids get distant colours of a 20-colour map
    ids = np.unique(part)
    rank = np.searchsorted(ids, part[:-1][same])
    from matplotlib import colormaps

    cmap = colormaps["tab20"]
    colors = cmap(((rank * 7) % 20) / 19.0)
    ax.add_collection(LineCollection(segs, colors=colors, linewidths=1.3, alpha=0.95))
    cur = srt[srt["frame"] == frame]
    ax.scatter(cur["x_px"], cur["y_px"], s=90, facecolors="none", edgecolors="r", lw=1)
    ax.set_xlim(-0.5, nx - 0.5)
    ax.set_ylim(ny - 0.5, -0.5)
    ax.set_axis_off()
    if pixel_size is None:
        pixel_size = (table.attrs.get("ptrack", {}) or {}).get("pixel_size")
    if pixel_size:
        bar = _scale_bar_um(nx * pixel_size * UM)
        L = bar / (pixel_size * UM)
        x0, y0 = nx * 0.04, ny * 0.95
        ax.plot([x0, x0 + L], [y0, y0], "-", color="w", lw=4, solid_capstyle="butt")
        ax.text(x0 + L / 2, y0 - ny * 0.02, f"{bar:g} µm", color="w", ha="center", va="bottom", fontsize=10)
    txt = title or f"frame {frame}: {len(cur)} detections (red), {len(ids)} tracks"
    ax.text(0.01, 0.99, txt, transform=ax.transAxes, color="w", va="top", ha="left", fontsize=9,
            bbox={"facecolor": "k", "alpha": 0.5, "pad": 2, "lw": 0})
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_D_per_particle(per: pd.DataFrame, axis: str = "xy", path=None, ax=None, D_ensemble=None,
                        D_stokes_einstein=None, D_hindered=None, label_ensemble: str = "ensemble"):
    """Each track's D with its closed-form error, sorted, against the ensemble and Stokes-Einstein.

    Parameters
    ----------
    per : DataFrame
        :func:`ptrack.motion.particle_diffusion` result (``D_<axis>``, ``D_<axis>_err``, ``n_frames``).
    axis : str
    path : path-like, optional
    ax : matplotlib Axes, optional
    D_ensemble, D_stokes_einstein, D_hindered : float, optional
        m^2/s, drawn as horizontal lines.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, ax = _axes(ax, figsize=(7, 4.2))
    D = per[f"D_{axis}"].to_numpy(float)
    E = per[f"D_{axis}_err"].to_numpy(float)
    ok = np.isfinite(D) & np.isfinite(E)
    o = np.argsort(D[ok])
    Ds, Es = D[ok][o] * UM2, E[ok][o] * UM2
    r = np.arange(len(Ds))
    ax.errorbar(r, Ds, yerr=Es, fmt="o", ms=3, color="C0", elinewidth=0.8, capsize=1.5,
                label=f"track (CVE, ± closed-form error; {ok.sum()} tracks)")
    if D_ensemble is not None:
        ax.axhline(D_ensemble * UM2, color="C1", lw=1.5, label=f"{label_ensemble}: {D_ensemble * UM2:.3g} µm²/s")
    if D_stokes_einstein is not None:
        ax.axhline(D_stokes_einstein * UM2, color="k", ls="--", lw=1,
                   label=f"Stokes-Einstein: {D_stokes_einstein * UM2:.3g} µm²/s")
    if D_hindered is not None:
        ax.axhline(D_hindered * UM2, color="C2", ls=":", lw=1.5,
                   label=f"Stokes-Einstein × wall ratio: {D_hindered * UM2:.3g} µm²/s")
    ax.set_xlabel("track (sorted by D)")
    ax.set_ylabel(f"D_{axis} (µm²/s)")
    ax.set_title("D per track: spread expected from each track's error", fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_cm_vs_z(table: pd.DataFrame, path=None, ax=None):
    """GDPT correlation Cm of each localisation against its height z."""
    fig, ax = _axes(ax, figsize=(6, 4))
    cm = table["cm"] if "cm" in table else np.ones(len(table))
    ax.scatter(table["z"] * UM, cm, s=3, alpha=0.4)
    ax.set_xlabel("z (µm)")
    ax.set_ylabel("Cm")
    ax.set_title("GDPT correlation against height")
    fig.tight_layout()
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_velocity(df: pd.DataFrame, vel: pd.DataFrame, path=None, profile: pd.DataFrame | None = None,
                  title: str | None = None, v_ref: float | None = None):
    """Tracks coloured by each particle's drift speed, and v against z with error bars.

    The left panel is a side view (x against z) for 3D tables, the image
    plane (x, y) for 2D ones.

    Parameters
    ----------
    df : DataFrame
        Trajectories table.
    vel : DataFrame
        :func:`particle_velocity` result.
    path : path-like, optional
        Also write a PNG here (atomically).
    profile : DataFrame, optional
        :func:`velocity_profile` result; without it the right panel shows each
        particle's v_z (or in-plane speed for 2D tables) against its mean z
        (or a histogram of speeds).
    v_ref : float, optional
        A reference velocity (m/s, e.g. the Henry velocity) drawn as a line.
    """
    from matplotlib.collections import LineCollection

    from .motion.tracks import COMPONENTS

    fig, (ax0, ax1) = new_figure(figsize=(11, 4.6), dpi=110, ncols=2)
    srt = df.sort_values(["particle", "frame"], kind="stable")
    part = srt["particle"].to_numpy()
    from .motion.velocity import default_axes

    side = "z" in default_axes(srt)       # the one axes rule: a z that changes
    x = srt["x"].to_numpy(dtype=float) * 1e6
    # 3D: side view (x against height z) shows the approach to the electrode; 2D: the image plane
    y = srt["z" if side else "y"].to_numpy(dtype=float) * 1e6
    same = part[1:] == part[:-1]
    segs = np.stack([np.c_[x[:-1], y[:-1]], np.c_[x[1:], y[1:]]], axis=1)[same]
    speed_of = pd.Series(vel["speed"].to_numpy(float) * 1e6, index=vel["particle"].to_numpy())
    sp = speed_of.reindex(part[:-1][same]).to_numpy()
    good = np.isfinite(sp)
    if good.any():
        lc = LineCollection(segs[good], array=sp[good], cmap="viridis", linewidths=1.2)
        ax0.add_collection(lc)
        fig.colorbar(lc, ax=ax0, label="drift speed |v| (µm/s)")
    if (~good).any():
        ax0.add_collection(LineCollection(segs[~good], colors="0.7", linewidths=0.8))
    ax0.autoscale()
    ax0.set_xlabel("x (µm)")
    if side:
        ax0.set_ylabel("height z (µm)")
        ax0.set_title("tracks (side view) coloured by drift speed")
    else:
        ax0.set_aspect("equal", adjustable="datalim")
        ax0.invert_yaxis()
        ax0.set_ylabel("y (µm)")
        ax0.set_title("tracks coloured by drift speed")
    has_z = "vz" in vel.columns and np.isfinite(vel["vz"].to_numpy(float)).any()
    if profile is not None and len(profile):
        zc = profile["z_mean"].fillna(profile["z_mid"]).to_numpy(float) * 1e6
        for i, c in enumerate(COMPONENTS):
            v = profile[f"v{c}"].to_numpy(float)
            if np.isfinite(v).any():
                ax1.errorbar(v * 1e6, zc, xerr=np.nan_to_num(profile[f"v{c}_err"].to_numpy(float)) * 1e6, fmt="o-",
                             ms=4, color=f"C{i}", elinewidth=0.8, capsize=2, label=f"v_{c} (± SE)")
        ax1.set_xlabel("drift velocity (µm/s)")
        ax1.set_ylabel("height z (µm)")
        ax1.set_title("velocity against height (bins)")
    elif has_z:
        ax1.errorbar(vel["vz"] * 1e6, vel["z_mean"] * 1e6, xerr=vel["vz_err"] * 1e6, fmt="o", ms=3,
                     elinewidth=0.7, label="v_z per particle (± SE)")
        ax1.set_xlabel("v_z (µm/s)")
        ax1.set_ylabel("mean height z (µm)")
        ax1.set_title("per-particle v_z against height")
    else:
        s = vel["speed"].to_numpy(float) * 1e6
        ax1.hist(s[np.isfinite(s)], bins=20, color="C0")
        ax1.set_xlabel("in-plane drift speed (µm/s)")
        ax1.set_ylabel("particles")
        ax1.set_title("drift speeds")
    if v_ref is not None and (profile is not None or has_z):
        ax1.axvline(v_ref * 1e6, color="k", ls="--", lw=0.8, label=f"reference {v_ref * 1e6:.3g} µm/s")
    if ax1.get_legend_handles_labels()[0]:
        ax1.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_wall_ratios(a: float, heights=(), ratio=None, ax=None, path=None):
    """D/D0 near a wall against the gap, for every parallel and perpendicular law of :mod:`ptrack.motion.wall`.

    Parameters
    ----------
    a : float
        Particle radius, m.
    heights : sequence of float
        Centre heights (m) marked by vertical lines.
    ratio : float, optional
        A measured D/D0 marked by a horizontal line.
    ax, path : optional
        Axes to draw into; PNG to write.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from .motion import wall

    fig, ax = _axes(ax, figsize=(6.4, 4.4))
    x = 1.0 + np.geomspace(1e-4, 1e2, 600)
    h = x * a
    g = (h - a) * UM
    ax.plot(g, wall.parallel_ratio(h, a, "auto"), "k-", label="parallel, recommended (GCB + Faxen)")
    ax.plot(g, wall.parallel_ratio(h, a, "faxen"), "b--", label="parallel, Faxen to (a/h)^5")
    ax.plot(g, wall.parallel_ratio(h, a, "first_order"), "c:", label="parallel, eq. 4.1 (1 - 9/16 a/h)")
    ax.plot(g, wall.perpendicular_ratio(h, a, "brenner"), "r-", label="perpendicular, Brenner")
    ax.plot(g, wall.perpendicular_ratio(h, a, "bevan_prieve"), "m--", label="perpendicular, Bevan-Prieve")
    for hm in heights:
        ax.axvline((hm - a) * UM, color="0.5", lw=0.8)
    if ratio is not None:
        ax.axhline(ratio, color="0.5", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("gap h - a between particle surface and wall (µm); h = centre height")
    ax.set_ylabel("D / D0")
    ax.set_ylim(0, 1.02)
    ax.set_title(f"hindered diffusion near a wall, radius a = {a * 1e9:.4g} nm")
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    if path is not None:
        save_figure(fig, path)
    return fig
