"""What our extra detections on trackpy's real movie are (issue: at most 10 % extras against trackpy's 344).

Frame 1 of trackpy's own brightfield test movie (``../shared/data/real/trackpy_image_sequence``), located by
``ptrack.locate`` with no option.  A detection is *matched* when one of trackpy's 344 reference positions
(``trackpy.locate(255 - frame, diameter=9, minmass=140)``) lies within 1 px; the others are *extras*.  Each
extra is then looked up among the features trackpy's own ``locate`` reports with its two cuts relaxed
(``minmass=0, separation=5``) and sorted by the cut that removed it from the reference:

- ``minmass``: trackpy's mass 100-140, i.e. above the valley of trackpy's own mass histogram (~100) but below
  its ``minmass=140``;
- ``separation``: trackpy's mass >= 140, dropped by its default ``separation = diameter + 1 = 10`` px because a
  brighter feature lies within 10 px;
- ``faint``: trackpy's mass below 100 (the dim or strongly defocused population);
- ``not trackpy``: no relaxed trackpy feature within 1 px (mostly defocused particles wider than trackpy's
  9 px window, whose centre trackpy puts elsewhere or not at all).

Beside each class: the share of its detections whose trajectory (the five frames located by
``ptrack.locate.batch`` and linked by ``ptrack.link.link``, as ``ptrack track`` does) holds every frame. A false
detection from noise does not come back at the same place in the next frames; a particle does.

Prints the table and writes ``--png`` (default ``bench/out/real_extras.png``): the frame, contrast-stretched,
with every detection circled by class, and trackpy's mass histogram with each class's masses.

Run: ``.venv/bin/python bench/bench_real_extras.py`` (a few seconds).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

REAL = ROOT.parent / "shared" / "data" / "real" / "trackpy_image_sequence"
CLASSES = ("matched", "minmass", "separation", "faint", "not trackpy")
COLOURS = {"matched": "#2ca02c", "minmass": "#ff9f1c", "separation": "#1f77b4", "faint": "#d62ad6",
           "not trackpy": "#d62728"}


def classify(xy, ref, tp_xy, tp_mass, max_px=1.0):
    """Class of each detection (``CLASSES``) from its nearest reference position and nearest relaxed
    trackpy feature.

    Parameters
    ----------
    xy : (N, 2) array, our positions (x, y) in px.
    ref : (M, 2) array, trackpy's reference positions (x, y) in px.
    tp_xy, tp_mass : (K, 2) and (K,) arrays, trackpy's features at relaxed cuts and their masses (trackpy's
        units: summed band-passed intensity).
    max_px : match radius (px).

    Returns
    -------
    (N,) array of str.

    Examples
    --------
    >>> import numpy as np
    >>> classify(np.array([[0., 0.], [20., 0.]]), np.array([[0.2, 0.]]), np.array([[20., 0.3]]), np.array([120.]))
    array(['matched', 'minmass'], dtype='<U11')
    """
    from scipy.spatial import cKDTree

    d_ref = cKDTree(ref).query(xy)[0]
    d_tp, k = cKDTree(tp_xy).query(xy)
    m = np.where(d_tp < max_px, tp_mass[np.minimum(k, len(tp_mass) - 1)], np.nan)
    out = np.full(len(xy), "not trackpy", dtype="<U11")
    out[m < 100] = "faint"
    out[(m >= 100) & (m < 140)] = "minmass"
    out[m >= 140] = "separation"
    out[d_ref < max_px] = "matched"
    return out


def cut_tradeoff(xy, values, ref, keep_above=True, max_px=1.0):
    """The best one can do with one cut on one of our columns: keep the detections whose value is at or above
    (or, ``keep_above=False``, at or below) a threshold, for every threshold the values offer.

    Returns ``(extras at the strictest cut that still finds >= 95 % of ref, found at the loosest cut that leaves
    <= 10 % extras)``, both as fractions of ``len(ref)`` (NaN where no cut reaches it).

    Examples
    --------
    >>> import numpy as np
    >>> ref = np.array([[0., 0.], [10., 0.]])
    >>> xy = np.array([[0., 0.], [10., 0.], [20., 0.]])
    >>> cut_tradeoff(xy, np.array([5., 4., 1.]), ref)
    (0.0, 1.0)
    """
    from scipy.spatial import cKDTree

    matched = cKDTree(ref).query(xy)[0] < max_px
    best_extra, best_found = np.nan, np.nan
    for t in np.unique(values):
        keep = values >= t if keep_above else values <= t
        if not keep.any():
            continue
        found = float((cKDTree(xy[keep]).query(ref)[0] < max_px).mean())
        extra = float((keep & ~matched).sum() / len(ref))
        if found >= 0.95:
            best_extra = extra if np.isnan(best_extra) else min(best_extra, extra)
        if extra <= 0.10:
            best_found = found if np.isnan(best_found) else max(best_found, found)
    return float(best_extra), float(best_found)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--png", type=Path, default=ROOT / "bench" / "out" / "real_extras.png")
    a = p.parse_args(argv)
    if not (REAL / "frames").is_dir():
        print(f"error: {REAL} not found: the shared real data are needed (see its README)", file=sys.stderr)
        return 2
    import cv2
    import pandas as pd
    import trackpy

    from ptrack.link import link
    from ptrack.image.detect import FALSE_ALARM_RATE
    from ptrack.locate import batch

    trackpy.quiet()
    paths = sorted((REAL / "frames").glob("*.png"))
    frames = [cv2.imread(str(q), cv2.IMREAD_UNCHANGED) for q in paths]
    im = frames[0]                                  # T76S3F00001.png, the reference's frame
    ref = pd.read_csv(REAL / "reference" / "trackpy_locate_frame0.csv")[["x", "y"]].to_numpy()
    # the whole movie located and linked as ptrack track does (frame 0's rows: locate(im) with no option); for
    # persistence: a false detection (noise) does not come back at the same place in the next frames, a
    # particle (or a speck stuck on the glass) does
    movie = link(batch(frames))
    df = movie[movie["frame"] == 0].reset_index(drop=True)
    track_len = movie.groupby("particle")["frame"].nunique().reindex(df["particle"].to_numpy()).to_numpy()
    xy = df[["x_px", "y_px"]].to_numpy()
    tp = trackpy.locate(255 - im, diameter=9, minmass=0, separation=5)
    cls = classify(xy, ref, tp[["x", "y"]].to_numpy(), tp["mass"].to_numpy())
    from scipy.spatial import cKDTree

    found = (cKDTree(xy).query(ref)[0] < 1.0).mean()
    print(f"ptrack.locate, no option: {len(df)} detections; trackpy's reference: {len(ref)} positions, "
          f"{100 * found:.1f} % of them found within 1 px")
    print(f"{'class':<12} {'count':>6} {'% of 344':>9} {'our size px (median)':>21} {'our SNR (median)':>17} "
          f"{'in all %d frames' % len(paths):>17}")
    for c in CLASSES:
        s = cls == c
        print(f"{c:<12} {s.sum():>6d} {100 * s.sum() / len(ref):>8.1f}% {np.median(df['size'][s]) if s.any() else np.nan:>21.2f} "
              f"{np.median(df['snr'][s]) if s.any() else np.nan:>17.1f} "
              f"{100 * np.mean(track_len[s] == len(paths)) if s.any() else np.nan:>16.1f}%")
    n_extra = int((cls != "matched").sum())
    print(f"extras: {n_extra} = {100 * n_extra / len(ref):.1f} % of {len(ref)} (the issue's goal: <= 10 %); "
          f"removed from the reference by trackpy's minmass or separation cut: "
          f"{int(np.isin(cls, ('minmass', 'separation')).sum())}; found again in all {len(paths)} frames: "
          f"{100 * np.mean(track_len[cls != 'matched'] == len(paths)):.1f} % (the false-alarm rate predicts "
          f"{FALSE_ALARM_RATE * im.size:.2f} false detections per frame)")
    # could a cut on one of our own columns (a minmass of ours) meet both goals? every threshold of each
    print("one cut on one of our columns, every threshold tried: fewest extras while >= 95 % found | most found "
          "while <= 10 % extras")
    for col, above in (("snr", True), ("signal", True), ("mass", True), ("photons", True), ("size", False),
                       ("ecc", False)):
        e, f_ = cut_tradeoff(xy, df[col].to_numpy(), ref, keep_above=above)
        print(f"  keep {col} {'>=' if above else '<='} t: {100 * e:5.1f} % extras | {100 * f_:5.1f} % found")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(15, 5.6), gridspec_kw={"width_ratios": [1.55, 1]})
    g = im.astype(float)
    lo, hi = np.percentile(g, [0.5, 99.5])
    ax.imshow(np.clip((g - lo) / (hi - lo), 0, 1), cmap="gray", interpolation="nearest")
    for c in CLASSES:
        s = cls == c
        ax.scatter(xy[s, 0], xy[s, 1], s=90, facecolors="none", edgecolors=COLOURS[c], linewidths=1.1,
                   label=f"{c} ({s.sum()})")
    ax.set_xlim(0, im.shape[1] - 1)
    ax.set_ylim(im.shape[0] - 1, 0)
    ax.set_title("trackpy's real movie, frame 1: ptrack.locate (no option), each detection by class")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    bins = np.arange(0, 320, 10)
    bx.hist(tp["mass"], bins=bins, color="0.75", label="all trackpy features (minmass 0, separation 5)")
    d_tp, k = cKDTree(tp[["x", "y"]].to_numpy()).query(xy)
    for c in ("matched", "minmass", "separation", "faint"):
        s = (cls == c) & (d_tp < 1.0)
        bx.hist(tp["mass"].to_numpy()[k[s]], bins=bins, histtype="step", lw=1.6, color=COLOURS[c],
                label=f"ours, {c}")
    bx.axvline(140, color="k", ls="--", lw=1)
    bx.text(142, bx.get_ylim()[1] * 0.92, "minmass = 140", fontsize=8)
    bx.set_xlabel("trackpy mass")
    bx.set_ylabel("features")
    bx.set_title("trackpy's mass of each of our detections")
    bx.legend(fontsize=8)
    fig.tight_layout()
    a.png.parent.mkdir(parents=True, exist_ok=True)
    tmp = a.png.with_name(a.png.stem + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    tmp.replace(a.png)
    print(f"wrote {a.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
