"""Heights of the pages of a calibration stack: a CSV beside the stack, the stack's own metadata, and a sanity check."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..errors import UserError
from .stack import TEMPLATE_SCALE

__all__ = ["z_csv_beside", "heights_from_metadata", "check_heights"]

# no objective's calibration spans more than this (working distances are mm; a stage scan is tens of um)
MAX_ABS_Z = 1e-3


def z_csv_beside(path) -> Path | None:
    """A heights CSV next to the stack: ``<stem>_z.csv``, ``<stem>.z.csv`` or ``calib_z.csv`` (first found)."""
    p = Path(path)
    if not p.is_file():
        return None
    stem = p.name
    for suf in (".ome.tiff", ".ome.tif", ".tiff", ".tif"):
        if stem.lower().endswith(suf):
            stem = stem[: -len(suf)]
            break
    for name in (f"{stem}_z.csv", f"{stem}.z.csv", "calib_z.csv"):
        q = p.parent / name
        if q.is_file():
            return q
    return None


def heights_from_metadata(path, n_pages: int, z0: float = 0.0):
    """Page heights (m) from a TIFF's own metadata, or None.

    Micro-Manager per-page stage positions (``ZPositionUm``), OME planes
    (``PositionZ``) or ``PhysicalSizeZ``, ImageJ ``spacing`` (with its
    ``unit``). A spacing gives ``z0 + k spacing``; absolute positions are
    kept as recorded (then shifted so that page 0 is at ``z0`` only if
    ``z0`` is given non-zero).

    Returns
    -------
    (z, description) or None
    """
    from ..io import parse_length

    p = Path(path)
    if not p.is_file() or p.suffix.lower() not in (".tif", ".tiff"):
        return None
    import tifffile

    try:
        with tifffile.TiffFile(str(p)) as tif:
            if tif.is_micromanager:
                zs = []
                for pg in tif.pages[:n_pages]:
                    tag = pg.tags.get("MicroManagerMetadata")
                    v = tag.value if tag is not None else {}
                    zz = v.get("ZPositionUm", v.get("Z-um")) if isinstance(v, dict) else None
                    if zz is None:
                        break
                    zs.append(float(zz) * 1e-6)
                if len(zs) == n_pages and np.ptp(zs) > 0:
                    z = np.array(zs)
                    return (z - z[0] + z0 if z0 else z), "Micro-Manager ZPositionUm"
                summ = (tif.micromanager_metadata or {}).get("Summary", {}) or {}
                if summ.get("z-step_um"):
                    return z0 + float(summ["z-step_um"]) * 1e-6 * np.arange(n_pages), "Micro-Manager z-step_um"
            if tif.is_ome and tif.ome_metadata:
                xml = tif.ome_metadata
                pos = re.findall(r'<Plane[^>]*\bPositionZ="([-0-9.eE+]+)"[^>]*?(?:PositionZUnit="([^"]+)")?', xml)
                if len(pos) >= n_pages:
                    z = np.array([parse_length(1.0, u or "um") * float(v) for v, u in pos[:n_pages]])
                    if np.ptp(z) > 0:
                        return (z - z[0] + z0 if z0 else z), "OME PositionZ"
                m = re.search(r'PhysicalSizeZ="([-0-9.eE+]+)"', xml)
                if m:
                    u = re.search(r'PhysicalSizeZUnit="([^"]+)"', xml)
                    dz = parse_length(float(m.group(1)), u.group(1) if u else "um")
                    if dz:
                        return z0 + dz * np.arange(n_pages), "OME PhysicalSizeZ"
            if tif.is_imagej:
                ij = tif.imagej_metadata or {}
                if ij.get("spacing"):
                    dz = parse_length(float(ij["spacing"]), ij.get("unit") or "um")
                    if dz:
                        return z0 + dz * np.arange(n_pages), "ImageJ spacing"
    except Exception:
        return None
    return None


def check_heights(z, what: str, calib=None):
    """Refuse heights no calibration stack can have.

    ``|z|`` above 1 mm (a step or origin in um given as m, or a wrong
    ``--calib-z0``); with a calibration of known pixel size, a stack whose
    particle image grows faster than 3 m per m of z (the geometric blur grows
    by tan(asin(NA/n)) per unit defocus: 2.4 at NA 1.4 in oil; a step in nm
    given as um, or far too small).
    """
    z = np.asarray(z, float)
    zmax = float(np.abs(z).max())
    if zmax > MAX_ABS_Z:
        raise UserError(f"calibration heights from {what} reach {zmax:g} m, beyond any objective's range",
                        "give heights in metres (a 2 µm step is 2e-6; --calib-z0 in m, e.g. -10e-6)")
    if calib is None or not calib.pixel_size or len(calib.templates) < 2:
        return
    sizes = np.array([t.shape[0] for t in calib.templates], float)
    grow = (sizes.max() - sizes.min()) / 2 / TEMPLATE_SCALE * calib.pixel_size     # 95 % light radius, m
    if calib.depth > 0 and grow / calib.depth > 3.0:
        raise UserError(f"calibration heights from {what} span {calib.depth * 1e6:.3g} µm while the particle image "
                        f"grows by {grow * 1e6:.3g} µm: the step is too small for these optics",
                        "give the stage step in metres (e.g. --calib-step 2e-6 for 2 µm)")
