"""Reading microscope movies frame by frame, with their calibration metadata.

A *movie* is a multi-page TIFF (classic, BigTIFF, OME-TIFF, ImageJ hyperstack,
Micro-Manager), or an image sequence (a folder or a glob of TIFF / PNG files,
one frame per file, natural sort order). :func:`open_movie` returns a
:class:`Movie` that reads one frame at a time: uncompressed contiguous data is
read frame by frame with positioned reads, anything else is decoded page by page, so a series never needs
its own size in RAM.

Pixel size (m, in the sample plane) and frame interval (s) are read from the
metadata (ImageJ ``unit``/XResolution/``finterval``, OME ``PhysicalSizeX`` and
``TimeIncrement`` with their units, Micro-Manager ``PixelSize_um`` and
``Interval_ms``, TIFF resolution in centimetres) and may be overridden.

Accepted pixel types: grayscale integers (8, 16, 32 bit, signed or unsigned),
i.e. camera counts. Floating-point images are refused unless
``allow_float=True`` (they are usually already processed, and their noise no
longer follows the camera model the localiser uses); RGB or multi-channel
images are refused (split the channels first).
"""
from __future__ import annotations

import contextlib
import glob
import logging
import os
import re
from pathlib import Path

import numpy as np

from .errors import UserError

__all__ = ["Movie", "open_movie", "parse_length", "parse_time", "check_not_blank"]

_LENGTH_UNITS = {
    "m": 1.0, "meter": 1.0, "metre": 1.0, "cm": 1e-2, "centimeter": 1e-2, "mm": 1e-3, "millimeter": 1e-3,
    "um": 1e-6, "µm": 1e-6, "μm": 1e-6, "micron": 1e-6, "microns": 1e-6, "micrometer": 1e-6,
    "micrometre": 1e-6, "nm": 1e-9, "nanometer": 1e-9, "nanometre": 1e-9,
}
_TIME_UNITS = {
    "s": 1.0, "sec": 1.0, "secs": 1.0, "second": 1.0, "seconds": 1.0, "ms": 1e-3, "msec": 1e-3,
    "millisecond": 1e-3, "milliseconds": 1e-3, "us": 1e-6, "µs": 1e-6, "μs": 1e-6,
    "microsecond": 1e-6, "microseconds": 1e-6, "ns": 1e-9, "min": 60.0, "minute": 60.0,
    "minutes": 60.0, "h": 3600.0, "hr": 3600.0, "hour": 3600.0,
}
_IMAGE_SUFFIXES = (".tif", ".tiff", ".png")


def _unit_factor(unit, table):
    if unit is None:
        return None
    u = str(unit).strip().replace("\\u00B5", "µ").replace("\\u00b5", "µ").lower()
    u = u.replace("u00b5", "µ")
    return table.get(u)


def _to_si(value, unit, table) -> float | None:
    """``value`` in ``unit`` times the unit's SI factor from ``table``; None if unknown or not positive."""
    f = _unit_factor(unit, table)
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    if f is None or not np.isfinite(v) or v <= 0:
        return None
    return v * f


def parse_length(value, unit) -> float | None:
    """Convert a length ``value`` in ``unit`` (``'um'``, ``'micron'``, ``'nm'``, ...) to metres.

    Returns None for an unknown unit (e.g. ImageJ's ``'pixel'``) or a
    non-positive value.
    """
    return _to_si(value, unit, _LENGTH_UNITS)


def parse_time(value, unit) -> float | None:
    """Convert a time ``value`` in ``unit`` (``'s'``, ``'ms'``, ``'sec'``, ...) to seconds (None if unknown)."""
    return _to_si(value, unit, _TIME_UNITS)


def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]


class _LogCapture(logging.Handler):
    """Collect tifffile's warnings (it logs, rather than raises, on many corrupt files)."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


@contextlib.contextmanager
def _capture_tifffile_log():
    h = _LogCapture()
    lg = logging.getLogger("tifffile")
    lg.addHandler(h)
    old = lg.propagate
    lg.propagate = False
    try:
        yield h
    finally:
        lg.removeHandler(h)
        lg.propagate = old


def _check_dtype(dtype, what, allow_float):
    dtype = np.dtype(dtype)
    if dtype.kind in "ui" and dtype.itemsize <= 4:
        return dtype
    if dtype.kind == "f" and allow_float:
        return dtype
    if dtype.kind == "f":
        raise UserError(
            f"{what} has floating-point pixels ({dtype.name}); ptrack expects grayscale integer camera counts",
            "give the raw camera movie (8/16-bit integer), or convert it to 16-bit (ImageJ: Image > Type > 16-bit)",
        )
    if dtype.kind == "b":
        raise UserError(f"{what} is a binary (1-bit) image", "give the grayscale camera movie")
    raise UserError(f"{what} has unsupported pixel type {dtype}", "give a grayscale 8/16/32-bit integer movie")


class Movie:
    """A movie opened for frame-by-frame reading (use :func:`open_movie`).

    Attributes
    ----------
    source : str
        The file, folder or glob the frames come from.
    n_frames : int
    shape : tuple of int
        Frame shape (rows, columns).
    dtype : numpy.dtype
    pixel_size : float or None
        m per pixel in the sample plane.
    frame_interval : float or None
        s between frames.
    memmapped : bool
        True if frames are read directly from contiguous uncompressed data
        (positioned reads, no decoding; nothing stays resident).
    """

    def __init__(self, source, reader, n_frames, shape, dtype, pixel_size, frame_interval,
                 memmapped=False, closer=None, info=None):
        self.source = str(source)
        self._reader = reader
        self.n_frames = int(n_frames)
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        self.pixel_size = pixel_size
        self.frame_interval = frame_interval
        self.memmapped = memmapped
        self._closer = closer
        self.info = dict(info or {})

    def __len__(self):
        return self.n_frames

    def __getitem__(self, i) -> np.ndarray:
        """Frame ``i`` as a 2D array (rows, columns) in the file's dtype."""
        i = int(i)
        if i < 0:
            i += self.n_frames
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame {i} out of range (movie has {self.n_frames})")
        try:
            a = self._reader(i)
        except UserError:
            raise
        except Exception as exc:
            raise UserError(f"cannot read frame {i} of {self.source}: {type(exc).__name__}: {exc}",
                            "the file is corrupt or truncated; re-export it") from None
        a = np.asarray(a)
        if a.shape != self.shape:
            a = a.reshape(self.shape)
        return a

    def __iter__(self):
        for i in range(self.n_frames):
            yield self[i]

    def require_calibration(self, need_time: bool = True) -> None:
        """Raise UserError if the pixel size (or frame interval) is unknown, naming the flag to give."""
        if self.pixel_size is None:
            raise UserError(f"{self.source} carries no pixel size in its metadata",
                            "give it with --pixel-size (m per pixel in the sample, e.g. 1.03e-7)")
        if need_time and self.frame_interval is None:
            raise UserError(f"{self.source} carries no frame interval in its metadata",
                            "give it with --frame-interval (s between frames, e.g. 0.1)")

    def close(self):
        if self._closer is not None:
            with contextlib.suppress(Exception):
                self._closer()
            self._closer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def __getstate__(self):  # movies are reopened by path in worker processes, never pickled
        raise TypeError("Movie objects hold open files; pass the path to worker processes instead")


def _tiff_calibration(tif, page):
    """(pixel_size m, frame_interval s, info) from a TiffFile's metadata."""
    px = dt = None
    info = {}
    # OME-XML
    if tif.is_ome and tif.ome_metadata:
        try:
            import xml.etree.ElementTree as ET

            root = ET.fromstring(tif.ome_metadata)
            pix = next((el for el in root.iter() if el.tag.endswith("Pixels")), None)
            if pix is not None:
                if pix.get("PhysicalSizeX"):
                    px = parse_length(pix.get("PhysicalSizeX"), pix.get("PhysicalSizeXUnit", "µm"))
                if pix.get("TimeIncrement"):
                    dt = parse_time(pix.get("TimeIncrement"), pix.get("TimeIncrementUnit", "s"))
                if dt is None:
                    planes = [el for el in pix if el.tag.endswith("Plane") and el.get("DeltaT")]
                    if len(planes) > 1:
                        ts = sorted(parse_time(p.get("DeltaT"), p.get("DeltaTUnit", "s")) or 0.0 for p in planes)
                        d = np.diff(ts)
                        d = d[d > 0]
                        if d.size:
                            dt = float(np.median(d))
            info["format"] = "ome"
        except Exception:
            pass
    # ImageJ
    if tif.is_imagej:
        ij = tif.imagej_metadata or {}
        info["format"] = "imagej"
        unit = ij.get("unit")
        if px is None and unit is not None and "XResolution" in page.tags:
            num, den = page.tags["XResolution"].value
            if num > 0 and den > 0:
                px = parse_length(den / num, unit)
        if dt is None:
            tunit = ij.get("tunit", "s")
            if ij.get("finterval"):
                dt = parse_time(ij["finterval"], tunit)
            elif ij.get("fps"):
                with contextlib.suppress(Exception):
                    dt = 1.0 / float(ij["fps"]) if float(ij["fps"]) > 0 else None
    # Micro-Manager
    if tif.is_micromanager:
        with contextlib.suppress(Exception):
            mm = tif.micromanager_metadata or {}
            summ = mm.get("Summary", mm.get("summary", {})) or {}
            if px is None and summ.get("PixelSize_um"):
                px = parse_length(summ["PixelSize_um"], "um")
            if dt is None and summ.get("Interval_ms"):
                dt = parse_time(summ["Interval_ms"], "ms")
            info["format"] = "micromanager"
    # plain TIFF resolution in centimetres (inches are nearly always a default 72 dpi: ignored)
    if px is None and "XResolution" in page.tags and "ResolutionUnit" in page.tags:
        with contextlib.suppress(Exception):
            if int(page.tags["ResolutionUnit"].value) == 3:
                num, den = page.tags["XResolution"].value
                if num > 0 and den > 0 and num != den:
                    px = parse_length(den / num, "cm")
    return px, dt, info


_TIME_AXES = "TIQ"      # time, generic image sequence, unknown pages: frames of the movie


def _frame_index(axes: str, shape: tuple, channel: int | None, plane: int | None, what: str):
    """Frames of a stack read by its axes: (n_frames, function frame -> flat page index).

    The leading axes (all but Y, X) are time-like (T, I, Q), Z (focal planes) or C (channels).
    Without a time-like axis longer than 1, Z is the frame axis (ImageJ saves a plain stack as
    slices). With both time and Z (or C) longer than 1 the planes (channels) are not frames: one
    is chosen by ``plane`` (``channel``), or the stack is refused as ambiguous.
    """
    lead = list(zip(axes[:-2], shape[:-2]))
    sizes = {a: n for a, n in lead}
    t_axes = [a for a, n in lead if a in _TIME_AXES and n > 1]
    if len(t_axes) > 1:
        raise UserError(f"{what} has several time-like axes {axes} {shape}", "re-export it as one time series")
    frame_axis = t_axes[0] if t_axes else ("Z" if sizes.get("Z", 1) > 1 else None)
    pick = {}
    for ax, opt, name in (("C", channel, "channel"), ("Z", plane, "plane")):
        n = sizes.get(ax, 1)
        if ax == frame_axis:
            if opt is not None and ax == "Z":
                raise UserError(f"--plane given but {what} has no time axis besides Z (axes {axes})",
                                "omit --plane: the Z slices are the frames")
            continue
        if n > 1 and opt is None:
            hint = "--channel N" if ax == "C" else "--plane N"
            raise UserError(f"{what} is a hyperstack (axes {axes}, shape {shape}) with {n} "
                            f"{'channels' if ax == 'C' else 'focal planes'}: which one is ambiguous",
                            f"choose one with {hint} (0..{n - 1})")
        if opt is not None and not 0 <= int(opt) < n:
            raise UserError(f"{name} {opt} is outside 0..{n - 1} of {what} (axes {axes})", f"give a {name} in 0..{n - 1}")
        pick[ax] = int(opt or 0)
    for a, n in lead:
        if a not in "CZ" and a != frame_axis and n > 1:
            raise UserError(f"{what} has an axis {a} of length {n} (axes {axes}) that is not time, Z or channel",
                            "re-export the movie as a time series of 2D frames")
    lead_shape = tuple(n for _, n in lead) or (1,)
    n_frames = sizes.get(frame_axis, 1) if frame_axis else 1

    def index(i):
        if not lead:
            return 0
        idx = tuple(i if a == frame_axis else pick.get(a, 0) for a, _ in lead)
        return int(np.ravel_multi_index(idx, lead_shape))
    return int(n_frames), index


def _open_tiff(path: Path, allow_float: bool, series_index: int | None = None, channel: int | None = None,
               plane: int | None = None):
    import tifffile

    size = path.stat().st_size
    with _capture_tifffile_log() as log:
        try:
            tif = tifffile.TiffFile(str(path))
        except Exception as exc:
            raise UserError(f"cannot read {path} as a TIFF file ({type(exc).__name__}: {exc})",
                            "give an uncorrupted TIFF movie (multi-page, ImageJ or OME-TIFF)") from None
        try:
            if not tif.series:
                raise UserError(f"{path} contains no readable image (corrupt, or not a movie)", "give an uncorrupted TIFF movie")
            if series_index is None:
                stacks = [k for k, sr in enumerate(tif.series) if len(sr.shape) >= 2 and min(sr.shape[-2:]) > 1
                          and getattr(sr, "kind", "") not in ("thumbnail",)]
                if len(stacks) > 1 and getattr(tif, "is_ome", False):       # several OME positions
                    raise UserError(f"{path} holds {len(stacks)} image series (positions) of shapes "
                                    f"{[tuple(tif.series[k].shape) for k in stacks][:4]}",
                                    "choose one with --series N")
                series_index = 0
            if not 0 <= int(series_index) < len(tif.series):
                raise UserError(f"series {series_index} is outside 0..{len(tif.series) - 1} of {path}",
                                f"give --series in 0..{len(tif.series) - 1}")
            series = tif.series[int(series_index)]
            page = series.pages[0] if series.pages else tif.pages[0]
            shape, axes = tuple(series.shape), series.axes
            len(tif.pages)      # walks the IFD chain: a file cut short loses its trailing IFDs (tifffile logs it)
            problems = [m for m in log.messages if re.search(r"corrupt|truncat|invalid|incomplete|not enough|missing", m, re.I)]
            if problems and all("imagej series metadata invalid" in m.lower() for m in problems) and \
                    len({tuple(pg.shape) for pg in tif.pages}) == 1:
                # tifffile could not place tiny ImageJ pages (e.g. 1x1 px) into a hyperstack: the file is
                # fine, its pages are the frames
                problems = []
                shape, axes = (len(tif.pages),) + tuple(tif.pages[0].shape), "I" + "YX"
                series = None
        except UserError:
            tif.close()
            raise
        except Exception as exc:
            tif.close()
            raise UserError(f"cannot read {path}: {type(exc).__name__}: {exc}", "the file is corrupt or truncated; re-export it") from None
    what = f"movie {path}"
    try:
        if problems:
            raise UserError(f"{path} is corrupt or truncated (tifffile: {problems[0]})",
                            "re-export or re-copy the file")
        if "S" in axes and shape[axes.index("S")] > 1 or getattr(page, "samplesperpixel", 1) > 1:
            raise UserError(f"{what} is RGB / has {getattr(page, 'samplesperpixel', 3)} samples per pixel; ptrack expects grayscale",
                            "give one grayscale channel (ImageJ: Image > Type > 16-bit, or Image > Color > Split Channels)")
        if axes.replace("C", "Z") != axes and not set(axes) - set("CYX") and shape[axes.index("C")] > 7:
            # an ImageJ stack written without axes metadata comes back as "CYX"; ImageJ composites
            # have at most 7 channels, so a longer C axis is a stack of frames
            axes = axes.replace("C", "Z")
        dtype = _check_dtype(series.dtype if series is not None else tif.pages[0].dtype, what, allow_float)
        if axes[-2:] != "YX" and len(shape) >= 2 and not axes.endswith("X"):
            raise UserError(f"{what} has unexpected axes {axes}", "give a stack of 2D grayscale frames")
        frame_shape = shape[-2:]
        n_pages = int(np.prod(shape[:-2])) if len(shape) > 2 else 1
        # frames by the axes: a TZYX / TCYX hyperstack is not T*Z frames
        n_frames, page_of = _frame_index(axes, shape, channel, plane, what)
        expected_bytes = n_pages * int(np.prod(frame_shape)) * dtype.itemsize
        px, dt, info = _tiff_calibration(tif, page)
        info["axes"] = axes
        offset = series.dataoffset if series is not None else None
        reader = None
        memmapped = False
        closer_fd = None
        if offset is not None:
            if offset + expected_bytes > size:
                raise UserError(
                    f"{path} is truncated: {n_frames} frames of {frame_shape[0]}x{frame_shape[1]} need "
                    f"{offset + expected_bytes} bytes, the file has {size}",
                    "re-copy or re-export the complete file")
            # contiguous uncompressed data: each frame is read straight from the file into a fresh
            # array (os.preadv), so neither the file nor a memory map of it stays resident
            bo = "<" if tif.byteorder == "<" else ">"
            fdtype = np.dtype(series.dtype).newbyteorder(bo)
            frame_bytes = int(np.prod(frame_shape)) * dtype.itemsize
            fd = os.open(str(path), os.O_RDONLY)
            memmapped = True

            def reader(i, fd=fd):
                a = np.empty(tuple(frame_shape), fdtype)
                got = os.preadv(fd, [memoryview(a).cast("B")], offset + page_of(i) * frame_bytes)
                if got != frame_bytes:
                    raise UserError(f"{path}: frame {i} is truncated", "re-copy or re-export the complete file")
                return a if fdtype.isnative else a.astype(fdtype.newbyteorder("="))

            closer_fd = fd
        else:
            # compressed / tiled / scattered strips: decode page by page
            pages = series.pages if series is not None else tif.pages
            if len(pages) != n_pages:
                raise UserError(f"{path}: {len(pages)} image pages for {n_pages} planes",
                                "the file is corrupt or truncated; re-export it")
            for p in pages:
                if p is None:
                    continue
                offs, counts = getattr(p, "dataoffsets", ()), getattr(p, "databytecounts", ())
                if offs and counts and max(o + c for o, c in zip(offs, counts)) > size:
                    raise UserError(f"{path} is truncated (image data of page {p.index} ends past the end of the file)",
                                    "re-copy or re-export the complete file")

            def reader(i, pages=pages):
                return pages[page_of(i)].asarray()
    except BaseException:
        tif.close()
        raise
    def closer():
        tif.close()
        if closer_fd is not None:
            os.close(closer_fd)

    return Movie(path, reader, n_frames, frame_shape, dtype, px, dt, memmapped=memmapped,
                 closer=closer, info=info)


def _read_single_image(p: Path):
    if p.suffix.lower() == ".png":
        import cv2

        a = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if a is None:
            raise UserError(f"cannot read image {p}", "the file is corrupt; re-export it")
        return a
    import tifffile

    return tifffile.imread(str(p))


def _open_sequence(files: list[Path], source: str, allow_float: bool):
    import tifffile

    first = files[0]
    a = _read_single_image(first)
    if a.ndim != 2:
        raise UserError(f"{first} is not a single grayscale image (shape {a.shape})",
                        "an image sequence needs one grayscale frame per file")
    dtype = _check_dtype(a.dtype, f"image sequence {source}", allow_float)
    px = dt = None
    info = {"format": "sequence", "files": len(files)}
    if first.suffix.lower() in (".tif", ".tiff"):
        with contextlib.suppress(Exception), tifffile.TiffFile(str(first)) as tif:
            px, dt, more = _tiff_calibration(tif, tif.pages[0])
    shape = a.shape

    def reader(i):
        b = _read_single_image(files[i])
        if b.shape != shape:
            raise UserError(f"{files[i]} has shape {b.shape}, the sequence's first image {shape}",
                            "all frames of a sequence must have the same size")
        return b

    return Movie(source, reader, len(files), shape, dtype, px, dt, info=info)


def open_movie(path, pixel_size: float | None = None, frame_interval: float | None = None,
               allow_float: bool = False, channel: int | None = None, plane: int | None = None,
               series: int | None = None) -> Movie:
    """Open a movie for frame-by-frame reading.

    Parameters
    ----------
    path : str or path-like
        A TIFF file (multi-page, BigTIFF, OME, ImageJ), a folder of TIFF/PNG
        frames, or a glob pattern such as ``'run1/*.tif'``.
    pixel_size : float, optional
        m per pixel in the sample plane; overrides the metadata.
    frame_interval : float, optional
        s between frames; overrides the metadata.
    allow_float : bool
        Accept floating-point images (refused by default).
    channel, plane : int, optional
        TCYX / TZYX hyperstacks are read by their axes (frames along T):
        the channel (C) or focal plane (Z) to read; a stack with several
        of them and no choice is refused as ambiguous. A stack with Z and no
        time axis is a time series of slices (ImageJ's plain stack).
    series : int, optional
        Image series (e.g. OME positions) of a multi-series file.

    Returns
    -------
    Movie

    Raises
    ------
    UserError
        Missing, corrupt or truncated file; RGB / multi-channel or
        floating-point pixels; frames of different sizes in a sequence.
    """
    from .errors import check_positive

    s = str(path)
    p = Path(s)
    if any(ch in s for ch in "*?[") and not p.exists():
        files = sorted((Path(f) for f in glob.glob(s) if Path(f).suffix.lower() in _IMAGE_SUFFIXES), key=_natural_key)
        if not files:
            raise UserError(f"no TIFF/PNG files match {s}", "check the pattern")
        movie = _open_sequence(files, s, allow_float)
    elif p.is_dir():
        files = sorted((f for f in p.iterdir() if f.suffix.lower() in _IMAGE_SUFFIXES and not f.name.startswith(".")),
                       key=_natural_key)
        if not files:
            raise UserError(f"folder {p} holds no .tif/.tiff/.png images", "give a movie file or a folder of frames")
        if len(files) == 1:
            movie = _open_tiff(files[0], allow_float, series, channel, plane) if files[0].suffix.lower() != ".png" \
                else _open_sequence(files, s, allow_float)
        else:
            movie = _open_sequence(files, s, allow_float)
    else:
        if not p.exists():
            raise UserError(f"movie not found: {p}", "check the path")
        if not os.access(p, os.R_OK):
            raise UserError(f"movie is not readable: {p}", "check its permissions")
        if p.suffix.lower() == ".png":
            movie = _open_sequence([p], s, allow_float)
        else:
            movie = _open_tiff(p, allow_float, series, channel, plane)
    if pixel_size is not None:
        movie.pixel_size = check_positive("pixel size", pixel_size)
    if frame_interval is not None:
        movie.frame_interval = check_positive("frame interval", frame_interval)
    return movie


def check_not_blank(movie: Movie, n_sample: int = 5) -> None:
    """Raise UserError if sampled frames carry no signal (all-dark or constant movie)."""
    idx = np.unique(np.linspace(0, movie.n_frames - 1, min(n_sample, movie.n_frames)).astype(int))
    lo, hi = np.inf, -np.inf
    for i in idx:
        f = movie[i]
        lo = min(lo, float(f.min()))
        hi = max(hi, float(f.max()))
    if hi <= lo:
        raise UserError(f"{movie.source} is blank: every sampled frame is the constant value {hi:g}",
                        "check the exposure / light source and that this is the right file")
