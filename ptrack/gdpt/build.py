"""From the pages of a calibration stack to the templates GDPT matches (see :func:`build_templates`)."""
from __future__ import annotations

import math

import numpy as np

from .interp import default_fine_step, interpolate_templates
from .stack import average_beads, bead_tracks, centred, cut_templates, find_beads, rejected_summary, require_pages

__all__ = ["build_templates", "fit_crop", "smooth_pages"]

# pages in the Savitzky-Golay (quadratic) smoothing of every pixel along z before the templates are cut
# (smooth_pages); 0 or 1: the pages as recorded. Brightfield (signed) stacks: 9 pages, which removes most of the
# z-dependent bias that template noise gives isolated particles. Fluorescence: none (on a fast-changing astigmatic
# focus in 0.1 um steps, smoothing blurred the templates and overlapping images got worse). Figures: README, GDPT.
Z_SMOOTH = 0
Z_SMOOTH_SIGNED = 9


def fit_crop(t, cy, cx, T: int):
    """Embed (crop or zero-pad) a template so that its centre (cy, cx) sits on the centre pixel of T x T."""
    return centred(t, cy, cx, T)


def smooth_pages(pages, z, window: int):
    """Each pixel's value smoothed along z by a quadratic Savitzky-Golay filter over ``window`` pages.

    One recorded page carries one noise realisation, and every match made
    with its template inherits it: the correlation of a noisy template with
    any image is lowered by ``1 / sqrt(1 + noise variance / signal variance)``,
    a factor that falls with defocus as the image spreads and fades, which
    tilts Cm(z) towards the sharper pages; with the page-to-page noise this
    gives a z bias that changes with z (epd_brightfield, isolated particles: about +0.06 um at
    1-5 um and -0.06 to -0.2 um at 10-12 um, with the shipped stack and with
    one rendered with another noise seed alike; with noise-free templates
    within +-0.04 um everywhere). The quadratic filter keeps every pixel's
    variation with z up to second order (also a slow lateral drift of the
    bead) and leaves ``3 (3 w^2 - 7) / (4 w (w^2 - 4))`` of the noise
    variance (0.49 for 5 pages, 0.26 for 9). Only for evenly stepped stacks
    of at least ``window`` pages (otherwise the pages are returned as they are).

    Parameters
    ----------
    pages : list of 2D float32 arrays (same shape), sorted by z
    z : array (K,), m
    window : int
        Odd number of pages (``Z_SMOOTH_SIGNED`` / ``Z_SMOOTH`` in
        :func:`build_templates`); < 3: no smoothing.

    Returns
    -------
    list of 2D float32 arrays
    """
    from scipy.signal import savgol_filter

    w = int(window)
    w = w if w % 2 else w - 1
    K = len(pages)
    dz = np.diff(np.asarray(z, float))
    if w < 3 or K < w or len({p.shape for p in pages}) != 1 or np.ptp(dz) > 0.01 * float(np.median(dz)):
        return pages
    st = savgol_filter(np.stack(pages).astype(np.float64), w, 2, axis=0, mode="interp")
    return [st[k].astype(np.float32) for k in range(K)]


def _ncc_same(a, b) -> float:
    a = a - a.mean()
    b = b - b.mean()
    d = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / d if d > 0 else -1.0


def _bead_offsets(per_bead, dense, dz, z_pages, page_of):
    """z of each bead's own pages read on the averaged (dense) calibration, minus the page height (m).

    Returns (n_beads, K) with NaN where a bead was not used; the spread between beads is the calibration's own
    z error and their mean per bead its tilt / field-dependent bias.
    """
    from ..calibration import _quadratic_peak

    K = len(z_pages)
    out = np.full((len(per_bead), K), np.nan)
    for i, b in enumerate(per_bead):
        for k in range(K):
            t = b["templates"][k]
            if t is None:
                continue
            js = np.nonzero(np.abs(page_of - k) <= 1)[0]
            c = np.full(len(dense), -1.0)
            for j in js:
                T = dense[j].shape[0]
                c[j] = _ncc_same(centred(t, b["centers"][k][0], b["centers"][k][1], T), dense[j])
            j = int(np.argmax(c))
            out[i, k] = _quadratic_peak(dz, c, j, n_points=5) - z_pages[k]
    return out


def _leave_one_out(cen, z, fine_step):
    """z error (m) of each interior page read on the calibration built without it (NaN at the ends).

    Page k (centred template) is matched by normalised cross-correlation
    against templates made from its neighbours only: interpolated between
    pages k - 1 and k + 1 when the calibration interpolates (``fine_step``),
    else pages k - 2, k - 1, k + 1, k + 2 (parabola through Cm(z)). The
    error holds the page's own noise, the neighbours' and the interpolation
    across twice the step: an honest (slightly pessimistic) z error of one
    image read on the calibration, where the spread between beads only says
    how well several beads agree.
    """
    from ..calibration import _quadratic_peak

    K = len(z)
    out = np.full(K, np.nan)
    for k in range(1, K - 1):
        if fine_step is not None:
            dense, dz, _, _ = interpolate_templates([cen[k - 1], cen[k + 1]], z[[k - 1, k + 1]], float(fine_step))
        else:
            idx = [j for j in (k - 2, k - 1, k + 1, k + 2) if 0 <= j < K]
            dense, dz = [cen[j] for j in idx], z[idx]
        c = np.array([_ncc_same(centred(cen[k], cen[k].shape[0] // 2, cen[k].shape[0] // 2, t.shape[0]), t)
                      for t in dense])
        j = int(np.argmax(c))
        out[k] = _quadratic_peak(dz, c, j, n_points=3) - z[k]
    return out


def build_templates(stack, z, signed: bool, template_size: int | None = None, max_beads: int | None = None,
                    fine_step: float | str | None = "auto"):
    """Templates of a calibration stack (pages sorted by z, brightfield already inverted).

    Parameters
    ----------
    stack : array (K, H, W) float32
    z : array (K,), increasing (m)
    signed : bool
        Brightfield (signed images).
    template_size : int, optional
        Fixed template side (px); default per page, from its image extent.
    max_beads : int, optional
        Use at most this many beads (the brightest).
    fine_step : float, "auto" or None
        Spacing (m) of templates interpolated between pages (:mod:`ptrack.gdpt.interp`); "auto":
        :func:`ptrack.gdpt.interp.default_fine_step`; None: the pages only.

    Returns
    -------
    templates, z, centers, info
    """
    K = len(z)
    found, pages = [], []
    for k in range(K):
        f, p, _ = find_beads(stack[k], signed=signed)
        found.append(f)
        pages.append(p)
    tracks = bead_tracks(found, max_beads)
    # the templates are cut from the pages smoothed along z (smooth_pages), at the places and sizes found on the
    # pages as recorded; the leave-one-out error below reads the unsmoothed pages (a smoothed page holds its
    # neighbours' noise, and its reading on the others would look better than an independent image's)
    raw_bead = cut_templates(pages, tracks, z, signed, template_size)
    smoothed = smooth_pages(pages, z, Z_SMOOTH_SIGNED if signed else Z_SMOOTH)
    per_bead = raw_bead if smoothed is pages else cut_templates(smoothed, tracks, z, signed, template_size)
    if not per_bead:
        per_bead = [{"templates": [None] * K, "why": ["no bead"] * K, "centers": np.zeros((K, 2)), "xy": (0, 0)}]
    bad = rejected_summary(per_bead, z)
    templates, centers, n_used = average_beads(per_bead, K)
    keep = np.array([t is not None for t in templates])
    require_pages(int(keep.sum()), bad, z)
    zk = z[keep]
    tk = [t for t, k in zip(templates, keep) if k]
    ck = centers[keep]
    info = {"n_beads": len(per_bead), "bead_xy": [b["xy"] for b in per_bead], "rejected": bad,
            "beads_per_page": n_used[keep].tolist(), "page_z": zk.copy(),
            "rejected_per_bead": [{k: w for k, w in enumerate(b["why"]) if w} for b in per_bead]}
    if fine_step == "auto":
        fine_step = default_fine_step(zk)
    step = float(np.median(np.diff(zk)))
    if fine_step is None or fine_step >= 0.99 * step or len(zk) < 2:
        info["n_sub"] = 1
        dense, dz, dc, page_of = tk, zk, ck, np.arange(len(zk))
    else:
        cen = [centred(t, c[0], c[1], t.shape[0]) for t, c in zip(tk, ck)]
        dense, dz, page_of, scales = interpolate_templates(cen, zk, float(fine_step))
        dc = np.array([(t.shape[0] // 2, t.shape[0] // 2) for t in dense], float)
        info["n_sub"] = int(round(step / float(fine_step)))
        info["page_scales"] = scales
    info["page_of"] = page_of
    # the honest z error: each interior page read on the calibration built without it (see _leave_one_out)
    if len(zk) >= 3:
        if per_bead is not raw_bead:
            t_raw, c_raw, _ = average_beads(raw_bead, K)
            tk, ck = [t for t, k in zip(t_raw, keep) if k], c_raw[keep]
        cen_all = [centred(t, c[0], c[1], t.shape[0]) for t, c in zip(tk, ck)]
        loo = _leave_one_out(cen_all, zk, None if info["n_sub"] == 1 else float(fine_step))
        info["page_loo_dz"] = loo
        # / sqrt 2: the page left out is read across twice the step; measured against truth, the RMS of the
        # leave-one-out errors is 1.2-2.1x the z RMSE of particles (bench_gdpt beads table, tests/test_gdpt.py,
        # data/synthetic diffusion3d and epd_brightfield), / sqrt 2 brings it to 0.85-1.6x
        info["z_error_loo"] = float(np.sqrt(np.nanmean(loo ** 2) / 2)) if np.isfinite(loo).any() else float("nan")
    if len(per_bead) > 1:
        kept = [dict(b, templates=[t for t, k in zip(b["templates"], keep) if k],
                     centers=b["centers"][keep]) for b in per_bead]
        off = _bead_offsets(kept, dense, dz, zk, page_of)
        info["bead_dz"] = off
        with np.errstate(invalid="ignore"):
            dev = off - np.nanmean(off, axis=0)
        n = np.sum(np.isfinite(off), axis=0)
        ok = n >= 2
        # the scatter of single beads about the average; the average of n beads scatters sqrt(n) times less
        info["z_error_bead"] = float(np.sqrt(np.nanmean(dev[:, ok] ** 2) * n[ok].mean() / max(n[ok].mean() - 1, 1)))\
            if ok.any() else float("nan")
        info["z_error_beads"] = info["z_error_bead"] / math.sqrt(max(float(n[ok].mean()), 1.0)) \
            if ok.any() else float("nan")
    # z_error: what one image read on this calibration is off by (leave-one-out), with the beads' disagreement
    # added in quadrature (the spread between beads alone was 3-6x below the measured error: bench_gdpt.py)
    parts = [info.get("z_error_loo", np.nan), info.get("z_error_beads", np.nan)]
    parts = [p for p in parts if np.isfinite(p)]
    info["z_error"] = float(math.sqrt(sum(p * p for p in parts))) if parts else float("nan")
    return dense, dz, dc, info
