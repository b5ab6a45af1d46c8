"""Views of deposits: PNG snapshots coloured by coordination number and an
extended-XYZ trajectory for OVITO.

* :func:`snapshot_png` draws one frame as a 3D scatter (marker area scaled to
  the particle radius) coloured by coordination number, like the seed's
  Figs. 3.17-3.22; :func:`snapshots_png` draws a row of frames.
* :func:`write_extxyz` writes frames in the extended XYZ format that OVITO,
  ASE and VMD open: per frame a count line, a comment line with
  ``Lattice="..." Properties=species:S:1:pos:R:3:radius:R:1:...`` and
  ``Time=``, then one line per particle.  Positions stay in metres.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ptrack.errors import atomic_output


def _figure(figsize):
    """A figure without pyplot: no backend switch, no global figure list (notebook-safe)."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def _unit(span: float):
    """(factor, name) putting a length span of this size (m) between 1 and 1000 units: m, mm, µm or nm."""
    for f, name in ((1.0, "m"), (1e3, "mm"), (1e6, "µm"), (1e9, "nm")):
        if span * f >= 1.0:
            return f, name
    return 1e9, "nm"


def _draw(ax, pos, radius, cn, vmax, box=None, title=None):
    """3D scatter in m, mm, µm or nm by the scene's size (metres give tick labels such as 2.5e-06 that smear)."""
    from matplotlib.ticker import MaxNLocator

    size = max(box[:2]) if box is not None else float(np.ptp(pos[:, :2])) if len(pos) else 1.0
    um, uname = _unit(size)
    x, y, z = pos[:, 0] * um, pos[:, 1] * um, pos[:, 2] * um
    r = radius * um
    # marker size ~ radius in axis units (approximate; matplotlib sizes are in points^2)
    span = max(np.ptp(x) if len(x) else 1.0, np.ptp(y) if len(y) else 1.0, 1e-9)
    s = (r / span * 210.0) ** 2
    sc = ax.scatter(x, y, z, c=cn, cmap="viridis", vmin=0, vmax=vmax, s=s, depthshade=True, edgecolors="none")
    if box is not None:
        ax.set_xlim(0, box[0] * um)
        ax.set_ylim(0, box[1] * um)
    ztop = max(float((z + r).max()) if len(z) else 1.0, 1e-9)
    ax.set_zlim(0, ztop)
    xs = box[0] * um if box is not None else max(np.ptp(x), 1e-9)
    ys = box[1] * um if box is not None else max(np.ptp(y), 1e-9)
    # a flat deposit gets a thin but readable z axis: at least a quarter of the width
    ax.set_box_aspect((xs, ys, min(max(ztop, 0.25 * max(xs, ys)), 2 * max(xs, ys))))
    ax.zaxis.set_major_locator(MaxNLocator(3))
    ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.yaxis.set_major_locator(MaxNLocator(4))
    ax.tick_params(labelsize=7, pad=0)
    ax.set_xlabel(f"x ({uname})", fontsize=8, labelpad=2)
    ax.set_ylabel(f"y ({uname})", fontsize=8, labelpad=2)
    ax.set_zlabel(f"z ({uname})", fontsize=8, labelpad=2)
    if title:
        ax.set_title(title, fontsize=9)
    return sc


def _colorbar(fig, sc, rect):
    """Colour bar in its own axes at ``rect`` (figure fraction): never over an axis label."""
    cax = fig.add_axes(rect)
    fig.colorbar(sc, cax=cax, label="coordination number")


def snapshot_png(path, pos, radius, cn, box=None, title=None, vmax=None):
    """One frame as a 3D scatter coloured by coordination number (PNG)."""
    fig = _figure((6.8, 5))
    ax = fig.add_axes([0.0, 0.02, 0.80, 0.92], projection="3d")
    vmax = vmax if vmax is not None else max(12, int(np.max(cn)) if len(cn) else 12)
    sc = _draw(ax, np.asarray(pos), np.asarray(radius), np.asarray(cn), vmax, box, title)
    _colorbar(fig, sc, [0.88, 0.2, 0.025, 0.6])
    with atomic_output(path, None) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return Path(path)


def snapshots_png(path, frames, box=None, vmax=None):
    """Several frames side by side; ``frames`` = list of (t, pos, radius, cn)."""
    k = len(frames)
    ncol = 2 if k == 4 else k
    nrow = (k + ncol - 1) // ncol
    fig = _figure((5.2 * ncol + 0.8, 4.6 * nrow))
    vmax = vmax if vmax is not None else max([12] + [int(np.max(f[3])) for f in frames if len(f[3])])
    sc = None
    width = 0.92 / ncol                       # the right 8 % holds the colour bar
    for a, (t, pos, radius, cn) in enumerate(frames):
        r, c = divmod(a, ncol)
        ax = fig.add_axes([c * width, 1 - (r + 1) / nrow + 0.01, width * 0.98, 0.88 / nrow], projection="3d")
        sc = _draw(ax, np.asarray(pos), np.asarray(radius), np.asarray(cn), vmax, box, f"t = {t:.3g} s")
    if sc is not None:
        _colorbar(fig, sc, [0.94, 0.2, 0.012, 0.6])
    with atomic_output(path, None) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    return Path(path)


def write_extxyz(path, frames, box=None, periodic=(False, False, False), extra_names=()):
    """Write frames as extended XYZ (OVITO-readable).

    Parameters
    ----------
    path : path-like
    frames : iterable of dict
        Each with ``t`` (s), ``pos`` (N, 3) m, ``radius`` (N,) m, and optional
        per-particle arrays named in ``extra_names`` (e.g. ``cn``, ``q6``) and
        ``vel`` (N, 3) m/s.
    box : (3,) edge lengths (m), optional
        Written as the ``Lattice`` with ``pbc``.
    """
    with atomic_output(path, "w") as fh:
        for fr in frames:
            pos = np.asarray(fr["pos"], dtype=float)
            n = len(pos)
            props = "species:S:1:pos:R:3:radius:R:1"
            cols = [pos, np.asarray(fr["radius"], dtype=float)[:, None]]
            if "vel" in fr:
                props += ":velo:R:3"
                cols.append(np.asarray(fr["vel"], dtype=float))
            for name in extra_names:
                a = np.asarray(fr[name])
                kind = "I" if np.issubdtype(a.dtype, np.integer) or a.dtype == bool else "R"
                props += f":{name}:{kind}:1"
                cols.append(a.astype(int if kind == "I" else float)[:, None])
            header = f'Properties={props} Time={float(fr["t"]):.9g}'
            if box is not None:
                L = [float(v) for v in box]
                header = (f'Lattice="{L[0]:.9g} 0 0 0 {L[1]:.9g} 0 0 0 {L[2]:.9g}" '
                          f'pbc="{" ".join("T" if p else "F" for p in periodic)}" ') + header
            fh.write(f"{n}\n{header}\n")
            data = np.hstack(cols) if cols else np.empty((n, 0))
            isint = []
            for c in cols:
                isint += [np.issubdtype(c.dtype, np.integer)] * c.shape[1]
            for row in data:
                fh.write("P " + " ".join(str(int(v)) if ii else f"{v:.9g}" for v, ii in zip(row, isint)) + "\n")
    return Path(path)
