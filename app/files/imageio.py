"""Reading camera images and recordings from disk for ``tirdeflect process``.

Supported inputs
----------------
- PNG, BMP, JPEG (8 or 16 bit, grey or colour; colour is converted to grey with
  OpenCV's luma weights and a log message says so),
- TIFF of 8 to 16 bit per sample, including camera TIFFs with *packed* 10- or
  12-bit samples (tifffile decodes them through imagecodecs), float32/64 TIFF,
  and multi-page TIFF stacks (each page one frame; a stack cut short by an
  interrupted copy gives every frame it declares, those it lost as errors that
  say it is truncated: :mod:`app.files.tiffpages`),
- the app's HDF5 recordings (``docs/recording-format.md``): frames from the
  ``/frames`` dataset ``(n, rows, cols)``, the reference from ``/reference``
  when the recording holds one,
- video (AVI, MKV, MP4, MOV through PyAV), Photron MRAW + CIH/CIHX (pyMRAW)
  and Phantom CINE (PIMS): see :mod:`app.files.formats`,
- folders and glob patterns of images, in natural order (``frame_2`` before
  ``frame_10``): :func:`expand_inputs`.

:func:`iter_frames` is the one reader of frame sequences: it yields
:class:`FrameItem` lazily, one frame decoded at a time, with the frame's time
in seconds (``time_s``) where the file has one. ``docs/inputs.md`` lists what
each format provides.

Values are returned **unscaled**: a packed 10-bit TIFF gives ``uint16`` values in
0..1023 and :attr:`ImageInfo.bits` says 10. Nothing is stretched to 16 bit, so
noise and saturation keep their meaning (saturation is ``2**bits - 1``). The
numerics accept any unsigned integer depth <= 16 and floats.

Everything that goes wrong raises :class:`ImageReadError` (a
:class:`processing.errors.TirdeflectError`) whose message names the file, the
problem and what to do.
"""

from __future__ import annotations

import glob as _glob
import logging
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from app.files import formats, tiffpages
from app.files.formats import ImageInfo, ImageReadError
from processing.errors import TirdeflectError

__all__ = [
    "attr_text",
    "ImageReadError",
    "ImageInfo",
    "FrameItem",
    "IMAGE_SUFFIXES",
    "TIFF_SUFFIXES",
    "HDF5_SUFFIXES",
    "read_image",
    "read_reference",
    "recording_has_reference",
    "image_info",
    "count_frames",
    "frame_count",
    "stands_for_one_frame",
    "iter_frames",
    "write_image",
    "recording_geometry_toml",
    "pre_trigger_span",
    "expand_inputs",
    "natural_key",
    "input_notes",
    "parse_frame_range",
    "average_frames",
]

log = logging.getLogger(__name__)

TIFF_SUFFIXES = frozenset({".tif", ".tiff"})
HDF5_SUFFIXES = frozenset({".h5", ".hdf5", ".hdf"})
CV2_SUFFIXES = frozenset({".png", ".bmp", ".jpg", ".jpeg", ".pgm", ".ppm"})
IMAGE_SUFFIXES = TIFF_SUFFIXES | HDF5_SUFFIXES | CV2_SUFFIXES
#: Every file suffix tirdeflect reads (images, stacks, recordings, video, camera files).
INPUT_SUFFIXES = (IMAGE_SUFFIXES | formats.VIDEO_SUFFIXES | formats.MRAW_SUFFIXES
                  | formats.CINE_SUFFIXES)
#: Multi-frame kinds read through :mod:`app.files.formats`.
_SOURCE_KINDS = ("video", "mraw", "cine")

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


@dataclass(frozen=True)
class FrameItem:
    """One frame of an input sequence.

    Attributes
    ----------
    image : numpy.ndarray
        Shape ``(rows, cols)``, dtype uint8, uint16 or float32/64, unscaled.
    source : str
        Path of the file it came from.
    index_in_source : int
        Page of a TIFF stack or index into ``/frames`` of a recording; 0 for
        plain images.
    sequence_index : int
        Position in the whole input sequence before ``first/last/step``
        selection (0-based), which is what ``--first/--last/--step`` count.
    camera_frame_id, device_timestamp_ns, host_timestamp_ns, flags : int
        From a recording's ``/frame_table`` row (camera block id, device and
        host clocks in ns, :class:`drivers.base.FrameFlags`); -1 (flags 0)
        when unknown, e.g. for image files.
    trigger_index : int or None
        Frames from the trigger frame (0; negative before it) from a triggered
        recording's ``/frame_table``; None when the source has none.
    frames_in_source : int
        Number of frames in the source file (1 for plain images).
    error : ImageReadError or None
        Set (and ``image`` None) when this frame could not be read and
        :func:`iter_frames` was asked to go on (``errors="yield"``).
    time_s : float
        Time of the frame in seconds where the file has one: relative to the
        trigger (MRAW, CINE), the stream start (video) or the recording's
        first frame (HDF5, from the device clock, else the host clock); NaN
        for image files.
    """

    image: np.ndarray | None
    source: str
    index_in_source: int
    sequence_index: int
    camera_frame_id: int = -1
    device_timestamp_ns: int = -1
    host_timestamp_ns: int = -1
    flags: int = 0
    frames_in_source: int = 1
    error: Exception | None = None
    time_s: float = math.nan
    trigger_index: int | None = None

    @property
    def label(self) -> str:
        """Human-readable name, e.g. ``rec.h5[17]`` or ``frame_0003.png``."""
        if self.frames_in_source == 1:
            return self.source
        return f"{self.source}[{self.index_in_source}]"


# --------------------------------------------------------------------------- checks


def _check_path(path) -> Path:
    """Existence and file-type checks with messages that say what to do."""
    p = Path(os.fspath(path))
    if not p.exists():
        hint = ""
        if any(ch in str(p) for ch in "*?["):
            hint = " (the pattern matched no file: check the directory and the spelling)"
        raise ImageReadError(f"input file {str(p)!r} does not exist{hint}; check the path")
    if p.is_dir():
        raise ImageReadError(
            f"input {str(p)!r} is a directory, not an image; pass the folder as a frame "
            f"input (its images are read in natural order) or the files, e.g. {str(p / '*.png')!r}"
        )
    if p.stat().st_size == 0:
        raise ImageReadError(f"input file {str(p)!r} is empty (0 bytes); re-export or re-record it")
    return p


def _kind(p: Path) -> str:
    kind = formats.kind_of(p)
    if kind is not None:
        return kind
    suffix = p.suffix.lower()
    with open(p, "rb") as fh:
        head = fh.read(8)
    if head == _HDF5_SIGNATURE or suffix in HDF5_SUFFIXES:
        return "recording"
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+") or suffix in TIFF_SUFFIXES:
        return "tiff"
    return "image"


def _to_gray(image: np.ndarray, p: Path) -> np.ndarray:
    """Reduce a colour image to one channel, or raise if it cannot be an image."""
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] in (1, 3, 4):
        import cv2

        if image.shape[2] == 1:
            return image[:, :, 0]
        # A grey image stored as RGB has three equal channels: take one exactly.
        if np.array_equal(image[:, :, 0], image[:, :, 1]) and np.array_equal(
            image[:, :, 1], image[:, :, 2]
        ):
            return np.ascontiguousarray(image[:, :, 0])
        log.info("%s is a colour image; converting to grey (OpenCV luma weights)", p)
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(np.ascontiguousarray(image), code)
    raise ImageReadError(
        f"{str(p)!r} holds an array of shape {image.shape}, not a single image of "
        f"(rows, cols); save one grey frame per file or a TIFF stack of grey pages"
    )


def _check_finite(image: np.ndarray, p: Path) -> np.ndarray:
    """A float image must hold finite samples: a NaN or Inf pixel would spread
    through every Fourier coefficient, so such an image is refused whole."""
    bad = ~np.isfinite(image)
    if bad.any():
        n = int(np.count_nonzero(bad))
        r, c = (int(v) for v in np.argwhere(bad)[0])
        raise ImageReadError(
            f"{str(p)!r} holds {n} NaN or infinite sample(s) (the first at row {r}, column {c}); "
            f"tirdeflect needs finite pixel values: pass the raw camera image, not a processed one"
        )
    return image


def _check_dtype(image: np.ndarray, p: Path) -> np.ndarray:
    if image.dtype in (np.uint8, np.uint16):
        return image
    if image.dtype == np.float32:
        return _check_finite(image, p)
    if image.dtype == np.bool_:
        return image.astype(np.uint8)
    if np.issubdtype(image.dtype, np.integer):
        info = np.iinfo(image.dtype)
        lo, hi = int(image.min()), int(image.max())
        if lo >= 0 and hi <= 65535:
            log.info("%s: %s samples in %d..%d stored as uint16", p, image.dtype, lo, hi)
            return image.astype(np.uint16)
        raise ImageReadError(
            f"{str(p)!r} has {image.dtype} samples in {lo}..{hi} (type range "
            f"{info.min}..{info.max}); tirdeflect reads unsigned 8-16 bit or float images: "
            f"convert it to uint16 or float32 TIFF"
        )
    if np.issubdtype(image.dtype, np.floating):
        return _check_finite(image.astype(np.float32, copy=False), p)
    raise ImageReadError(
        f"{str(p)!r} has samples of type {image.dtype}; tirdeflect reads unsigned "
        f"8-16 bit integer or float images"
    )


def _bits_of(dtype: np.dtype) -> int:
    return int(np.dtype(dtype).itemsize * 8)


# --------------------------------------------------------------------------- TIFF


def _tiff_open(p: Path):
    import tifffile

    # tifffile logs what it cannot parse (e.g. "invalid offset to first page"); its
    # records are kept from the user's log while it reads for us (tiffpages.quiet_tifffile)
    # and the ImageReadError raised here says it in the user's terms instead
    logging.getLogger("tifffile").setLevel(logging.ERROR)
    try:
        with tiffpages.quiet_tifffile():
            return tifffile.TiffFile(p)
    except Exception as exc:  # tifffile raises TiffFileError, ValueError, struct errors...
        truncated = tiffpages.header_cut(p)
        if truncated:
            raise ImageReadError(f"{str(p)!r} is truncated: {truncated}; copy the file again "
                                 f"from its source") from exc
        raise ImageReadError(
            f"{str(p)!r} is not a readable TIFF ({type(exc).__name__}: {exc}); "
            f"check that the file is complete and really a TIFF"
        ) from exc


def _page_data_end(pages, i: int) -> int:
    """Byte just past the pixel data of TIFF page ``i`` (0 if unknown)."""
    try:
        page = pages[i]
        return max((int(o) + int(n) for o, n in zip(page.dataoffsets, page.databytecounts)),
                   default=0)
    except Exception:
        return 0


def _tiff_layout(tif, p: Path):
    """Return (n_frames, shape, dtype, bits, reader) for a TIFF file.

    ``n_frames`` is what the file declares (:func:`app.files.tiffpages.stack_extent`),
    so that a stack cut short by an interrupted copy loses no frame in silence: each
    frame it no longer holds is an ImageReadError of ``reader``, saying so.
    ``reader(i)`` returns frame ``i`` as a 2-D array.
    """
    pages = tif.pages
    with tiffpages.quiet_tifffile() as said:
        listed = len(pages)
        extent = tiffpages.stack_extent(tif, p, listed, bool(said))
    if extent.pages == 0:
        truncated = tiffpages.header_cut(p)
        if truncated:
            raise ImageReadError(f"{str(p)!r} is truncated: {truncated}; copy the file again "
                                 f"from its source")
        raise ImageReadError(f"{str(p)!r} is a TIFF with no image pages")
    first = pages.first if hasattr(pages, "first") else pages[0]
    bits = int(first.bitspersample)
    spp = int(getattr(first, "samplesperpixel", 1))
    depth = int(getattr(first, "imagedepth", 1) or 1)
    if depth != 1:
        raise ImageReadError(
            f"{str(p)!r} has volume pages (image depth {depth}); tirdeflect reads TIFF "
            f"pages of one grey (rows, cols) image each"
        )
    if spp not in (1, 3, 4):
        raise ImageReadError(
            f"{str(p)!r} has {spp} samples per pixel; save grey (1) or RGB (3) images"
        )
    rows, cols = int(first.imagelength), int(first.imagewidth)
    planes = _planes_of_a_stack(tif, first, extent.pages, spp, rows, cols, p)
    dtype = np.dtype(first.dtype) if first.dtype is not None else None
    if dtype is None:
        raise ImageReadError(
            f"{str(p)!r} uses a TIFF sample format tifffile cannot decode "
            f"(bits per sample {bits}); install imagecodecs or re-save as 16-bit TIFF"
        )

    def reader(i: int) -> np.ndarray:
        if planes:  # one frame per plane of the one page (see _planes_of_a_stack)
            if not 0 <= i < planes:
                raise ImageReadError(f"{str(p)!r} holds {planes} frames (0 to {planes - 1}); there is no frame {i}")
            with tiffpages.quiet_tifffile():
                plane = tiffpages.plane_of_page(p, first, i, planes, tif.byteorder)
                return _check_dtype(np.ascontiguousarray(plane), p)
        try:
            with tiffpages.quiet_tifffile():
                if i >= extent.pages:  # declared, its directory lost: ImageReadError if cut off
                    arr = tiffpages.frame_beyond_pages(p, extent, i, first, tif.byteorder)
                else:
                    arr = pages[i].asarray()
        except ImageReadError:
            raise
        except Exception as exc:
            with tiffpages.quiet_tifffile():
                end = _page_data_end(pages, i)
            size = p.stat().st_size
            if end > size:
                raise ImageReadError(
                    f"page {i} of {str(p)!r} is truncated: its pixels end at byte {end} but the "
                    f"file is {size} bytes long (an interrupted copy or recording); copy the file "
                    f"again from its source"
                ) from exc
            raise ImageReadError(
                f"page {i} of {str(p)!r} cannot be decoded ({type(exc).__name__}: {exc}); "
                f"it may use a compression imagecodecs lacks: re-save it uncompressed"
            ) from exc
        if arr.ndim == 3 and arr.shape[0] in (3, 4) and arr.shape[1:] == (rows, cols):
            arr = np.moveaxis(arr, 0, -1)  # planar RGB (SYX) to YXS
        if arr.shape[:2] != (rows, cols):
            raise ImageReadError(
                f"page {i} of {str(p)!r} has shape {arr.shape[:2]} but page 0 has "
                f"{(rows, cols)}; a stack must hold frames of one size"
            )
        arr = _to_gray(arr, p)
        return _check_dtype(arr, p)

    out_dtype = np.dtype(np.float32) if dtype.kind == "f" else dtype
    if dtype.kind == "f":
        bits = _bits_of(dtype)
    return planes or extent.declared, (rows, cols), out_dtype, bits, reader


#: TIFF files already said to be read plane by plane (:func:`_planes_of_a_stack`), with their size and mtime
_PLANES_SAID: set = set()


def _planes_of_a_stack(tif, first, pages: int, spp: int, rows: int, cols: int, p: Path) -> int:
    """The number of grey frames (3 or 4) of a TIFF whose one page is an RGB(A) image of separate planes that
    tifffile wrote from a ``(3 or 4, rows, cols)`` array (its description ``{"shape": [3, rows, cols]}``),
    else 0. ``tifffile.imwrite(np.stack(frames))`` of 3 or 4 frames stores them so unless told
    ``photometric="minisblack"`` (it warns that its next versions will store separate grey pages): read as
    one colour image, two or three frames were lost in silence (by-hand trial of 7 Dec 2026: "wrote 1
    frame(s)"). Said once per file as a warning."""
    import tifffile

    shaped = [m for m in (getattr(tif, "shaped_metadata", None) or ()) if isinstance(m, dict)]
    if not (pages == 1 and spp in (3, 4) and int(getattr(first, "planarconfig", 1)) == int(
            tifffile.PLANARCONFIG.SEPARATE) and shaped and list(shaped[0].get("shape", ())) == [spp, rows, cols]):
        return 0
    key = (str(p), p.stat().st_size, p.stat().st_mtime_ns)
    if key not in _PLANES_SAID:
        _PLANES_SAID.add(key)
        log.warning("%s holds a (%d, %d, %d) array that tifffile stored as one colour image of separate planes "
                    "(tifffile.imwrite without photometric='minisblack'): read as %d grey frames, as tifffile's "
                    "next versions store it; a colour image is saved with its planes last (rows, cols, %d)",
                    p.name, spp, rows, cols, spp, spp)
    return spp


# --------------------------------------------------------------------------- HDF5


def h5_open_error(p: Path, exc: OSError, *, what: str = "recording") -> ImageReadError:
    """The one-line error for an HDF5 file ``p`` that h5py cannot open (``exc``): cut
    short, held by the process writing it (HDF5's file lock), or damaged; ``what``
    names it in the message (a recording, or an output of ``tirdeflect process``)."""
    text = str(exc)
    m = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", text)
    if m:
        return ImageReadError(
            f"{str(p)!r} is truncated: it is {m.group(1)} bytes long but its header says "
            f"{m.group(2)} (an interrupted copy?); copy the file again from its source")
    if "lock" in text.lower() or "errno = 11" in text or "Errno 11" in text:
        return ImageReadError(
            f"{str(p)!r} is being written by another process (HDF5's file lock: a `tirdeflect "
            f"process` or `record` run, or the GUI, still has it open); wait until that run has "
            f"finished, or read a copy of the file")
    return ImageReadError(
        f"{str(p)!r} is not a readable HDF5 {what} ({exc}); its first block (the HDF5 "
        f"superblock) is damaged or it is no HDF5 file: copy it again from its source, or "
        f"check it with `h5dump -H`")


def h5_damaged(p: Path, what: str, exc: BaseException) -> ImageReadError:
    """The one-line error for a part ``what`` (e.g. ``"/reference"``) of the HDF5 file
    ``p`` that opens but cannot be read (``exc``: HDF5 finds damaged structures)."""
    detail = " ".join(str(exc).split()) or type(exc).__name__
    return ImageReadError(
        f"{str(p)!r} is damaged: {what} cannot be read (HDF5: {detail}); the file changed after "
        f"it was written (a failing disk or an interrupted copy): copy it again from its source "
        f"(`h5dump -H` shows which parts still read)")


def _h5_open(p: Path):
    import h5py

    try:
        return h5py.File(p, "r")
    except OSError as exc:
        raise h5_open_error(p, exc) from exc


class _h5_file:
    """``with _h5_file(p) as f``: the recording ``p`` open for reading; an HDF5 read error
    inside the block that nothing more precise caught becomes :func:`h5_damaged`."""

    def __init__(self, p: Path):
        self.p = p

    def __enter__(self):
        self.f = _h5_open(self.p)
        return self.f

    def __exit__(self, kind, exc, tb):
        self.f.close()
        if exc is not None and isinstance(exc, (OSError, RuntimeError, KeyError, ValueError)) \
                and not isinstance(exc, TirdeflectError):
            raise h5_damaged(self.p, "its HDF5 structure", exc) from exc
        return False


def _h5_frames(f, p: Path):
    import h5py

    ds = f.get("frames")
    if not isinstance(ds, h5py.Dataset):
        names = ", ".join(sorted(f.keys())) or "nothing"
        hint = ""
        if "height" in f:
            hint = " (this looks like a `tirdeflect process` output, not a recording)"
        raise ImageReadError(
            f"{str(p)!r} has no /frames dataset{hint}; it holds {names}. "
            f"tirdeflect process reads recordings made by `tirdeflect record` or the GUI"
        )
    if ds.ndim != 3:
        raise ImageReadError(
            f"/frames in {str(p)!r} has shape {ds.shape}; expected (n, rows, cols)"
        )
    n = int(ds.shape[0])
    # A recording that stopped early may say how many frames are complete.
    for key in ("frames_written", "frames_done", "n_frames"):
        if key in ds.attrs or key in f.attrs:
            done = int(ds.attrs.get(key, f.attrs.get(key)))
            if 0 <= done < n:
                n = done
            break
    return ds, n


def _h5_bits(f, ds) -> int:
    for holder in (ds.attrs, f.attrs):
        for key in ("bits", "bit_depth", "pixel_bits"):
            if key in holder:
                try:
                    return int(holder[key])
                except (TypeError, ValueError):
                    pass
    return _bits_of(ds.dtype)


def _h5_frame_table(f, n: int, p: Path):
    """The recording's ``/frame_table`` rows 0..n-1 as a structured array and the mask of
    its damaged rows (:func:`frame_table_damage`); (None, None) when it has none, or
    when it cannot be read at all (:func:`input_notes` says so)."""
    import h5py

    try:
        table = f.get("frame_table")
        if not isinstance(table, h5py.Dataset) or table.dtype.names is None:
            return None, None
        rows = table[: min(n, table.shape[0])]
    except (OSError, RuntimeError, KeyError) as exc:
        log.debug("%s: /frame_table cannot be read (%s)", p, exc)
        return None, None
    return rows, frame_table_damage(rows)


def frame_table_damage(table) -> np.ndarray:
    """Rows of a recording's frame table that cannot be what the recorder wrote, as a
    boolean mask (e.g. a chunk of the file overwritten with zeros).

    The recorder writes rows in the order the camera thread received the frames:
    ``sequence`` strictly increasing and ``host_timestamp_ns`` (the host's monotonic
    clock) never decreasing. A row that breaks this against the row before it is
    damaged; so is row 0 when it is all zeros and row 1 is damaged too (a zeroed
    stretch that starts at the first row).
    """
    names = table.dtype.names or ()
    n = len(table)
    bad = np.zeros(n, dtype=bool)
    if n < 2 or "sequence" not in names:
        return bad
    seq = table["sequence"].astype(np.int64)
    bad[1:] = seq[1:] <= seq[:-1]
    if "host_timestamp_ns" in names:
        host = table["host_timestamp_ns"].astype(np.int64)
        bad[1:] |= host[1:] < host[:-1]
    zero_row = np.ones(n, dtype=bool)
    for name in ("sequence", "frame_id", "device_timestamp_ns", "host_timestamp_ns"):
        if name in names:
            zero_row &= table[name] == 0
    bad[0] = bool(zero_row[0] and bad[1])
    # a zeroed stretch: its first row already breaks the order; the rows after it that
    # are zeros too are part of it (0 <= 0), and the first intact row after it ends it
    return bad


def _table_fields(table, i: int, bad=None) -> dict:
    if table is None or i >= len(table) or (bad is not None and bad[i]):
        return {}  # no row, or a damaged one: the frame's times, ids and flags are unknown
    row = table[i]
    names = table.dtype.names
    out = {}
    for key, name in (("camera_frame_id", "frame_id"), ("device_timestamp_ns", "device_timestamp_ns"),
                      ("host_timestamp_ns", "host_timestamp_ns"), ("flags", "flags"),
                      ("trigger_index", "trigger_index")):
        if name in names:
            out[key] = int(row[name])
    # time since the recording's first frame (its first intact row): camera clock, else host clock
    first = table[int(np.argmin(bad))] if bad is not None and not bad.all() else table[0]
    for name in ("device_timestamp_ns", "host_timestamp_ns"):
        if name in names and int(row[name]) >= 0 and int(first[name]) >= 0:
            out["time_s"] = (int(row[name]) - int(first[name])) * 1e-9
            break
    return out


def _row_checksum(table, i: int, bad=None):
    """The CRC32 the recorder stored for frame ``i`` (format 1.2), or None: no checksum
    in this file (older recordings), no row, or a damaged row."""
    if table is None or "crc32" not in (table.dtype.names or ()) or i >= len(table):
        return None
    if bad is not None and bad[i]:
        return None
    return int(table[i]["crc32"])


def _verify_checksum(image: np.ndarray, stored, p: Path, what: str) -> None:
    """Raise ImageReadError when ``image``'s bytes (as stored) do not give the CRC32
    ``stored`` (None: nothing to check)."""
    if stored is None:
        return
    import zlib

    actual = zlib.crc32(np.ascontiguousarray(image)) & 0xFFFFFFFF
    if actual != int(stored):
        raise ImageReadError(
            f"{what} of {str(p)!r} is corrupt: its pixels do not match the checksum the recorder "
            f"stored (CRC32 {int(stored):08x}, read {actual:08x}); the file changed after it was "
            f"recorded (a failing disk or an interrupted copy): copy it again from its source")


def _open_source(p: Path):
    return formats.open_source(p)


# --------------------------------------------------------------------------- public API


def image_info(path) -> ImageInfo:
    """Inspect an input file without reading all its pixels.

    Parameters
    ----------
    path : str or os.PathLike
        Image, TIFF (stack) or HDF5 recording.

    Returns
    -------
    ImageInfo

    Raises
    ------
    ImageReadError
        Missing file, directory, empty or unreadable file.
    """
    p = _check_path(path)
    kind = _kind(p)
    if kind in _SOURCE_KINDS:
        with _open_source(p) as src:
            return src.info()
    if kind == "tiff":
        with _tiff_open(p) as tif:
            n, shape, dtype, bits, _ = _tiff_layout(tif, p)
        return ImageInfo(p, kind, n, shape, dtype, bits)
    if kind == "recording":
        with _h5_file(p) as f:
            ds, n = _h5_frames(f, p)
            bits = _h5_bits(f, ds)
            dtype = np.dtype(np.float32) if ds.dtype.kind == "f" else np.dtype(ds.dtype)
            return ImageInfo(p, kind, n, tuple(int(s) for s in ds.shape[1:]), dtype, bits)
    image = read_image(p)
    return ImageInfo(p, kind, 1, image.shape, image.dtype, _bits_of(image.dtype))


def _read_cv2(p: Path) -> np.ndarray:
    import cv2

    # np.fromfile + imdecode copes with non-ASCII paths, which cv2.imread does not.
    try:
        buf = np.fromfile(p, dtype=np.uint8)
    except OSError as exc:
        raise ImageReadError(f"cannot read {str(p)!r}: {exc.strerror or exc}") from exc
    image = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageReadError(
            f"{str(p)!r} is not a readable image (OpenCV cannot decode its "
            f"{len(buf)} bytes as {p.suffix.upper().lstrip('.') or 'an image'}); "
            f"check the file is a complete PNG/BMP/TIFF"
        )
    return _check_dtype(_to_gray(image, p), p)


def read_image(path, *, index: int | None = None) -> np.ndarray:
    """Read one grey frame.

    Parameters
    ----------
    path : str or os.PathLike
        PNG/BMP/JPEG, TIFF (single page or stack) or HDF5 recording.
    index : int, optional
        Page of a TIFF stack / frame of a recording. Required when the file
        holds more than one frame (so that a stack is never silently reduced
        to its first page); ignored for single-frame files when 0 or None.

    Returns
    -------
    numpy.ndarray
        Shape ``(rows, cols)``, dtype uint8, uint16 (values unscaled, e.g.
        0..1023 for a 10-bit camera) or float32.

    Raises
    ------
    ImageReadError
        The file is missing, a directory, unreadable, not grey-convertible or
        the index is out of range.
    """
    p = _check_path(path)
    kind = _kind(p)
    if kind == "image":
        if index not in (None, 0):
            raise ImageReadError(f"{str(p)!r} holds one frame; index {index} does not exist")
        return _read_cv2(p)
    if kind in _SOURCE_KINDS:
        with _open_source(p) as src:
            i = _resolve_index(index, src.n_frames, p, what="frames")
            for _, image, _ in src.frames(range(i, i + 1)):
                return _check_dtype(_to_gray(image, p), p)
        raise ImageReadError(f"{str(p)!r}: frame {i} could not be decoded (the file ends early)")
    if kind == "tiff":
        with _tiff_open(p) as tif:
            n, _, _, _, reader = _tiff_layout(tif, p)
            i = _resolve_index(index, n, p, what="pages")
            return reader(i)
    with _h5_file(p) as f:
        ds, n = _h5_frames(f, p)
        i = _resolve_index(index, n, p, what="frames")
        table, bad = _h5_frame_table(f, n, p)
        return _h5_read(ds, i, p, _row_checksum(table, i, bad))


def _resolve_index(index, n: int, p: Path, *, what: str) -> int:
    if index is None:
        if n == 1:
            return 0
        raise ImageReadError(
            f"{str(p)!r} holds {n} {what}; say which one to use "
            f"(for the reference: --reference-index K)"
        )
    if not -n <= index < n:
        raise ImageReadError(f"{str(p)!r} holds {n} {what}; index {index} is out of range")
    return index % n


def read_reference(path, *, index: int | None = None, frames: slice | None = None,
                   pattern: str = "checkerboard") -> np.ndarray:
    """Read the reference (undeformed) image.

    A plain image or single-page TIFF is the reference itself. An HDF5
    recording provides its stored reference (``/reference``) when it has one,
    otherwise its first frame (logged). A multi-page TIFF needs ``index``.

    Parameters
    ----------
    path : str or os.PathLike
    index : int, optional
        Use this page of a TIFF stack / frame of a recording (``/frames``)
        as the reference, instead of the rules above.
    frames : slice, optional
        Average these frames of the file (``--reference-frames 0:20``), those that
        agree with the first (:func:`average_frames`). Not together with ``index``.
    pattern : str
        "checkerboard" or "dots": how :func:`average_frames` compares the frames.

    Returns
    -------
    numpy.ndarray
        Shape ``(rows, cols)``, dtype uint8/uint16/float32.
    """
    if frames is not None:
        if index is not None:
            raise ImageReadError("give either --reference-index or --reference-frames, not both")
        return average_frames(path, frames, pattern)
    p = _check_path(path)
    if index is not None:
        return read_image(p, index=index)
    if _kind(p) == "recording":
        import h5py

        with _h5_file(p) as f:
            ref = f.get("reference")
            if isinstance(ref, h5py.Dataset):
                try:
                    arr = np.asarray(ref[()])
                except (OSError, RuntimeError) as exc:
                    raise h5_damaged(p, "the reference image (/reference)", exc) from exc
                _verify_checksum(arr, ref.attrs.get("crc32"), p, "the reference image (/reference)")
                if arr.ndim == 3 and arr.shape[0] == 1:
                    arr = arr[0]
                return _check_dtype(_to_gray(arr, p), p)
            ds, n = _h5_frames(f, p)
            if n == 0:
                raise ImageReadError(f"recording {str(p)!r} holds no frames and no /reference")
            log.warning("recording %s has no /reference; using its first frame as reference", p)
            return _check_dtype(_to_gray(np.asarray(ds[0]), p), p)
    return read_image(p)


def frame_count(path, *, unreadable_as_frame: bool = False) -> int:
    """Number of frames in one file, reading headers only (plain images count 1
    without being decoded, so a broken PNG is only found when it is read; a TIFF
    stack counts the frames it declares, also those an interrupted copy cut off).

    With ``unreadable_as_frame`` an image or TIFF file that is empty or whose header
    cannot be read counts 1: :func:`iter_frames` with ``errors="yield"`` gives it as
    one unreadable frame, so that a run goes on past it (:func:`stands_for_one_frame`).

    Raises
    ------
    ImageReadError
        Missing file, directory, empty file, unreadable TIFF/HDF5 header (the last
        two not for images and TIFFs with ``unreadable_as_frame``).
    """
    try:
        p = _check_path(path)
        kind = _kind(p)
        if kind == "image":
            return 1
        if kind in _SOURCE_KINDS:
            with _open_source(p) as src:
                return src.n_frames
        if kind == "tiff":
            with _tiff_open(p) as tif:
                return _tiff_layout(tif, p)[0]
        with _h5_file(p) as f:
            return _h5_frames(f, p)[1]
    except ImageReadError:
        if unreadable_as_frame and stands_for_one_frame(path):
            return 1
        raise


def stands_for_one_frame(path) -> bool:
    """Whether an input file that cannot be opened (empty, or its header unreadable)
    stands for one unreadable frame of a run that goes on past it: an image or TIFF
    file, whose frame is then stored invalid with the reason. Not a missing path or a
    folder (a typing error: refused), nor a recording, video or camera file: how many
    frames it held is unknown, so every frame number after it (``--frames``) would be
    off by as many; those are refused before the run. (A TIFF stack whose first image
    directory is lost counts one frame too: nothing in it says how many it held.)"""
    p = Path(os.fspath(path))
    try:
        return p.is_file() and _kind(p) in ("image", "tiff")
    except OSError:
        return False


def recording_has_reference(path) -> bool:
    """Whether ``path`` is an HDF5 recording that stores its reference image (``/reference``)."""
    p = _check_path(path)
    if _kind(p) != "recording":
        return False
    import h5py

    with _h5_open(p) as f:
        return isinstance(f.get("reference"), h5py.Dataset)


def recording_geometry_toml(path) -> str | None:
    """Geometry TOML text stored in a recording (``/geometry_toml``), else None.

    Returns None for files that are not HDF5 recordings.
    """
    p = _check_path(path)
    if _kind(p) != "recording":
        return None
    import h5py

    with _h5_file(p) as f:
        try:
            node = f.get("geometry_toml")
            if isinstance(node, h5py.Dataset):
                damage = _vlen_heap_damage(p, node)
                if damage:  # HDF5 would loop for ever on it: never hand it to h5py
                    raise _geometry_damaged(p, ValueError(damage))
                value = node[()]
            elif "geometry_toml" in f.attrs:
                value = f.attrs["geometry_toml"]
            else:
                return None
            if isinstance(value, bytes):
                value = value.decode("utf-8")
        except (OSError, RuntimeError, KeyError, UnicodeDecodeError) as exc:
            raise _geometry_damaged(p, exc) from exc
    value = str(value)
    if not value.strip("\x00 \t\r\n") or "\x00" in value:  # the recorder never stores an empty one
        raise _geometry_damaged(p, ValueError(f"its text is {len(value)} characters of which "
                                              f"{value.count(chr(0))} are zero bytes"))
    return value


def _vlen_heap_damage(p: Path, ds) -> str:
    """Why the global heap behind the scalar variable-length string dataset ``ds`` of
    the file ``p`` must not be read (:func:`app.files.h5safe.global_heap_damage`), or
    "" (sound, or not a layout this checks)."""
    from app.files import h5safe

    try:
        if ds.shape != () or not ds.dtype.kind == "O":
            return ""
        offset = ds.id.get_offset()
        if offset is None:
            return ""
        with open(p, "rb") as fh:
            fh.seek(offset)
            descriptor = fh.read(16)  # length (4), collection address (8), object index (4)
    except (OSError, RuntimeError, ValueError):
        return ""
    if len(descriptor) < 16:
        return "its data lies past the end of the file"
    return h5safe.global_heap_damage(p, int.from_bytes(descriptor[4:12], "little"))


def _geometry_damaged(p: Path, exc: BaseException) -> ImageReadError:
    detail = " ".join(str(exc).split()) or type(exc).__name__
    return ImageReadError(
        f"the geometry stored in {str(p)!r} (/geometry_toml) is damaged ({detail}): give the "
        f"geometry with --geometry G.toml (the one the recording was made with), and copy the "
        f"recording again from its source")


def count_frames(paths: Sequence) -> int:
    """Total number of frames in ``paths`` (pages and recording frames counted;
    folders and globs expanded by :func:`expand_inputs`)."""
    return sum(frame_count(p) for p in expand_inputs(paths))


def iter_frames(
    paths: Sequence,
    *,
    first: int = 0,
    last: int | None = None,
    step: int = 1,
    errors: str = "raise",
    losses_from: int | None = None,
) -> Iterator[FrameItem]:
    """Yield the frames of several files in order, one at a time.

    Multi-frame files (TIFF stacks, recordings) are read page by page, so a
    long recording never has to fit in memory.

    Parameters
    ----------
    paths : sequence of path-like
        Input files in processing order; folders and glob patterns are
        expanded in natural order (:func:`expand_inputs`).
    first, last : int
        Sequence indices (0-based, counting every frame of every file in
        order) of the first and last frame to yield, both **inclusive**;
        ``last=None`` means to the end.
    step : int
        Yield every ``step``-th frame from ``first``; a recording's frame carries the loss flags of the
        frames stepped over before it, from ``losses_from`` on (default ``first``; a chunk of a longer
        selection gives the selection's frame before its own first): :func:`_stepped_over_losses`.
    errors : {"raise", "yield"}
        What a frame that cannot be read (undecodable image, truncated page, NaN samples) does:
        "raise" ends the iteration with its ImageReadError; "yield" yields a FrameItem with
        ``image=None`` and ``error`` set, and goes on with the next frame. An image or TIFF file that
        cannot be opened at all (empty, its header damaged) is with "yield" one such frame
        (:func:`stands_for_one_frame`); a recording, video or camera file whose frames cannot even be
        counted raises either way. A TIFF stack gives every frame it declares: those an interrupted
        copy cut off are such frames, saying the file is truncated.

    Yields
    ------
    FrameItem

    Raises
    ------
    ImageReadError
        When a file cannot be read; frames before it have already been
        yielded. Its ``sequence_index`` attribute is the failing frame's index.
        Also for bad ``first/last/step``.
    """
    selection = _checked_selection(first, last, step, errors, losses_from)

    def frame(read, path, i, seq, **fields):
        """The FrameItem of one frame; a read error raises or is yielded."""
        try:
            return FrameItem(read(), str(path), i, seq, **fields)
        except ImageReadError as exc:
            exc.sequence_index = seq
            if errors == "raise":
                raise
            return FrameItem(None, str(path), i, seq, error=exc, **fields)

    seq = 0
    try:
        for path in expand_inputs(paths):
            if last is not None and seq > last:
                return
            try:
                seq = yield from _file_frames(path, seq, selection, frame, errors)
            except ImageReadError as exc:
                if errors == "raise" or not stands_for_one_frame(path):
                    raise
                # an image or TIFF that cannot be opened (empty, header damaged): one unreadable
                # frame, as frame_count(unreadable_as_frame=True) counts it, and the run goes on
                exc.sequence_index = seq
                if _wanted(seq, selection):
                    yield FrameItem(None, str(path), 0, seq, error=exc)
                seq += 1
    except ImageReadError as exc:
        # say which frame of the sequence could not be read (the file is in the message)
        if getattr(exc, "sequence_index", None) is None:
            exc.sequence_index = seq
        raise


def _checked_selection(first: int, last, step: int, errors: str, losses_from=None) -> tuple:
    """``(first, last, step, losses_from)`` of :func:`iter_frames`, refused where they select nothing."""
    if step < 1:
        raise ImageReadError(f"--step must be >= 1; got {step}")
    if first < 0:
        raise ImageReadError(f"--first must be >= 0; got {first}")
    if last is not None and last < first:
        raise ImageReadError(f"--last ({last}) is before --first ({first}); nothing to process")
    if errors not in ("raise", "yield"):
        raise ValueError(f"errors must be 'raise' or 'yield'; got {errors!r}")
    return first, last, step, first if losses_from is None else int(losses_from)


def _wanted(k: int, selection: tuple) -> bool:
    """Whether sequence index ``k`` is picked by ``selection`` = (first, last, step, ...),
    last inclusive or None."""
    first, last, step = selection[:3]
    return k >= first and (last is None or k <= last) and (k - first) % step == 0


def _file_frames(path, seq: int, selection: tuple, frame, errors: str):
    """The FrameItems of one input file of :func:`iter_frames`, its first frame at sequence
    index ``seq``; ``frame`` makes each (or its error item), ``selection`` picks them
    (:func:`_wanted`). Returns the sequence index after the file's last frame, or one past
    ``last`` where the selection ends inside the file.

    Raises ImageReadError when the file itself cannot be opened (before any frame)."""
    first, last, step = selection[:3]
    p = _check_path(path)
    kind = _kind(p)
    if kind == "image":
        if _wanted(seq, selection):
            yield frame(lambda: _read_cv2(p), path, 0, seq)
        return seq + 1
    if kind in _SOURCE_KINDS:
        with _open_source(p) as src:
            picked = _local_range(seq, src.n_frames, first, last, step)
            # every frame the header promises comes: read, or as its error (the file
            # ends before it, its decoder failed): formats.Source.frames
            i = picked.start
            try:
                for i, image, time_s in src.frames(picked, errors=errors):
                    yield frame(lambda: _source_image(image, p), path, i, seq + i,
                                frames_in_source=src.n_frames, time_s=time_s)
            except ImageReadError as exc:
                exc.sequence_index = seq + getattr(exc, "index_in_source", i)
                raise
            return seq + src.n_frames
    if kind == "tiff":
        with _tiff_open(p) as tif:
            n, _, _, _, reader = _tiff_layout(tif, p)
            for i in range(n):
                if last is not None and seq > last:
                    return seq
                if _wanted(seq, selection):
                    yield frame(lambda: reader(i), path, i, seq, frames_in_source=n)
                seq += 1
        return seq
    with _h5_file(p) as f:
        ds, n = _h5_frames(f, p)
        table, bad = _h5_frame_table(f, n, p)
        # a recording made without a trigger counts its trigger_index from its first frame: no trigger to name
        untriggered = attr_text(f.attrs, "trigger_source") == "none"
        for i in range(n):
            if last is not None and seq > last:
                return seq
            if _wanted(seq, selection):
                crc = _row_checksum(table, i, bad)
                fields = _table_fields(table, i, bad)
                if untriggered:
                    fields.pop("trigger_index", None)
                skipped = range(max(0, i - step + 1, i - (seq - selection[3])), i)
                if "flags" in fields and len(skipped):
                    fields["flags"] |= _stepped_over_losses(table, bad, skipped)
                yield frame(lambda: _h5_read(ds, i, p, crc), path, i, seq, frames_in_source=n, **fields)
            seq += 1
    return seq


def attr_text(attrs, name: str) -> str:
    """The HDF5 string attribute ``name`` (str or bytes as stored) as str, "" when absent."""
    value = attrs.get(name, "")
    return value.decode(errors="replace") if isinstance(value, bytes) else str(value)


def _stepped_over_losses(table, bad, rows: range) -> int:
    """The loss flags (frames lost before them: camera id or time gaps, ring overruns) of the
    recording's frames ``rows``, stepped over by ``--step``, OR-ed: the next frame processed
    carries them, so that losses between two processed frames are never silent (a run with
    --step 3 over 3 frames the camera lost: time steps 0.03, 0.06 s, every flag 0, exit 0)."""
    from drivers.base import FrameFlags

    if table is None or "flags" not in (table.dtype.names or ()):
        return 0
    loss = int(FrameFlags.ID_GAP_BEFORE | FrameFlags.TIME_GAP_BEFORE | FrameFlags.RING_OVERRUN_BEFORE)
    flags = 0
    for r in rows:
        if r < len(table) and not (bad is not None and bad[r]):
            flags |= int(table[r]["flags"]) & loss
    return flags


def _source_image(image, p: Path) -> np.ndarray:
    """A frame from :meth:`formats.Source.frames`, or its read error raised."""
    if isinstance(image, Exception):
        raise image
    return _check_dtype(_to_gray(image, p), p)


def _h5_read(ds, i: int, p: Path, crc=None) -> np.ndarray:
    """Frame ``i`` of a recording's ``/frames``, checked against its CRC32 ``crc`` from
    the frame table (None: none stored); an HDF5 read error or a mismatch is an
    ImageReadError."""
    try:
        arr = np.asarray(ds[i])
    except (OSError, RuntimeError) as exc:
        raise h5_damaged(p, f"frame {i} (/frames)", exc) from exc
    _verify_checksum(arr, crc, p, f"frame {i}")
    return _check_dtype(_to_gray(arr, p), p)
# --------------------------------------------------------------------------- sequences

_DIGITS = re.compile(r"(\d+)")


def natural_key(path) -> tuple:
    """Sort key putting ``frame_2`` before ``frame_10`` (digit runs compare as numbers)."""
    parts = _DIGITS.split(str(path))
    return tuple((0, int(t), "") if t.isdigit() else (1, 0, t.lower()) for t in parts)


def _folder_frames(folder: Path) -> list:
    """A folder's image files (PNG/BMP/TIFF...) in natural order; a folder without
    images gives its recordings, videos and camera files instead."""
    files = [q for q in folder.iterdir() if q.is_file() and not q.name.startswith(".")]
    images = [q for q in files if q.suffix.lower() in (CV2_SUFFIXES | TIFF_SUFFIXES)]
    if not images:
        images = [q for q in files if q.suffix.lower() in INPUT_SUFFIXES]
        # a Photron recording is a .cih/.cihx + .mraw pair: open it once, through its header
        stems = {}
        for q in images:
            stems.setdefault(q.with_suffix("").name, set()).add(q.suffix.lower())
        images = [q for q in images if not (
            (q.suffix.lower() == ".mraw" and stems[q.with_suffix("").name] & {".cih", ".cihx"})
            or (q.suffix.lower() == ".cih" and ".cihx" in stems[q.with_suffix("").name]))]
    if not images:
        raise ImageReadError(
            f"folder {str(folder)!r} holds no image, recording, video or camera file "
            f"({', '.join(sorted(s.lstrip('.') for s in INPUT_SUFFIXES))}); check the folder")
    return sorted(images, key=natural_key)


def expand_inputs(paths: Sequence) -> list:
    """Input arguments as the files to read, in order.

    A folder gives its image files in natural order (``frame_2`` before
    ``frame_10``), or, when it holds no image, its recordings, videos and
    camera files; a glob pattern that is not itself a
    file (``'frames/*.tif'``, quoted so the shell leaves it) gives its matches
    in natural order; anything else is kept as given. A list of plain files
    given in an order that differs from the natural one (the shell sorts
    ``frame_10`` before ``frame_2``) is kept, with a warning.

    Raises
    ------
    ImageReadError
        A folder without input files, or a pattern matching nothing.
    """
    out = []
    for path in paths:
        p = Path(os.fspath(path))
        if p.is_dir():
            out.extend(str(q) for q in _folder_frames(p))
        elif not p.exists() and any(ch in str(p) for ch in "*?["):
            matches = [m for m in _glob.glob(str(p)) if Path(m).is_file()]
            if not matches:
                raise ImageReadError(
                    f"the pattern {str(p)!r} matches no file; check the folder and the spelling")
            out.extend(sorted(matches, key=natural_key))
        else:
            out.append(os.fspath(path))
    if len(out) > 2 and out == sorted(out) and out != sorted(out, key=natural_key):
        log.warning("the %d inputs are in alphabetical order (%s before %s), not natural order; "
                    "they are processed as given: pass the folder or a quoted glob for natural order",
                    len(out), Path(out[0]).name, Path(out[1]).name)
    return out


def input_notes(paths: Sequence) -> list:
    """Warnings about the inputs that the user must see (lossy video, colour to grey, a
    truncated file; a recording that did not end normally, or whose frame table is
    damaged: :func:`recording_notes`).

    Reads headers only (video, MRAW, CINE) and a recording's attributes and frame
    table; plain images add nothing.
    """
    notes = []
    for path in expand_inputs(paths):
        p = Path(os.fspath(path))
        if p.is_file() and formats.kind_of(p) is not None:
            with _open_source(_check_path(p)) as src:
                notes.extend(src.notes)
        elif p.is_file() and _kind(p) == "recording":
            notes.extend(recording_notes(p))
    return notes


def recording_notes(path) -> list:
    """What the user must know before trusting the frames of the recording ``path``:
    that it did not end normally (``complete`` = 0: no ``/summary``, e.g. a copy taken
    while it was recorded, or the recorder was killed; or it stopped on an error), and
    which rows of its ``/frame_table`` are damaged (:func:`frame_table_damage`)."""
    p = _check_path(path)
    notes = []
    with _h5_file(p) as f:
        ds, n = _h5_frames(f, p)
        attrs = f.attrs
        table, bad = _h5_frame_table(f, n, p)
        if "complete" in attrs and int(attrs["complete"]) == 0:
            planned = int(ds.attrs.get("frames_planned", -1))
            of = f" of the {planned} planned" if planned > n else ""
            node = f.get("geometry_toml")
            heap_damage = _vlen_heap_damage(p, node) if node is not None else ""
            error = "" if heap_damage else str(attrs.get("error", "") or "")
            span = pre_trigger_span(table, bad)
            untriggered = ("" if span is None else
                           f", all before its trigger (trigger_index {span[0]} to {span[1]}): it stopped before "
                           f"the trigger came, no frame is the trigger frame and the event is not in it")
            losses = "" if error or "summary" not in f else _summary_losses(f)
            if "summary" not in f:
                notes.append(
                    f"{p.name} is a recording that did not end normally (complete = 0, no /summary: "
                    f"the recorder was stopped hard, or this is a copy taken while it recorded"
                    + (f"; its error: {error}" if error else "")
                    + f"): it holds {n}{of} frames{untriggered}, and frames the camera sent may be "
                    f"missing; check the original recording")
            elif losses:  # it ran to its end; the frames lost on the way are why
                notes.append(f"{p.name} is a recording that lost frames on the way ({losses}): "
                             f"it holds {n}{of} frames{untriggered}")
            else:
                notes.append(f"{p.name} is a recording that ended early ({error or 'complete = 0'}): "
                             f"it holds {n}{of} frames{untriggered}")
        if n and table is None and "frame_table" in f:
            notes.append(f"{p.name}: /frame_table cannot be read (the file is damaged there): "
                         f"the frames' times, camera ids and flags are unknown")
        elif bad is not None and bad.any():
            k = np.flatnonzero(bad)
            notes.append(
                f"{p.name}: {len(k)} row(s) of /frame_table are damaged (frames {k[0]}..{k[-1]}: "
                f"sequence numbers or host times not increasing as the recorder writes them, e.g. "
                f"overwritten with zeros): those frames' times, camera ids and flags are unknown "
                f"(NaN / -1 in the output)"
                + (", their pixels unchecked (their checksums are in those rows)"
                   if "crc32" in (table.dtype.names or ()) else "")
                + "; copy the recording again")
    return notes


def _summary_losses(f) -> str:
    """The frames a recording's ``/summary`` says were lost (camera frame-id gaps, ring overruns), as words
    ("144 lost: 144 to ring overruns, the recorder behind the camera"); "" where none were or it cannot be
    read. A recording whose ring overran ran to its end with frames missing: "ended early (complete = 0)"
    said otherwise (sweep of 7 Dec 2026: 56 of 200 frames at 20 kHz through a 2-frame ring)."""
    import json

    try:
        s = json.loads(f["summary"].attrs["summary_json"])
    except Exception:  # noqa: BLE001 - no summary to read: nothing said here
        return ""
    upstream, overrun = int(s.get("lost_upstream_id_gaps", 0)), int(s.get("lost_ring_overrun", 0))
    if upstream + overrun <= 0:
        return ""
    parts = ([f"{overrun} to ring overruns, the recorder behind the camera"] if overrun else []) + (
        [f"{upstream} by the camera or its link (frame-id gaps)"] if upstream else [])
    return f"{upstream + overrun} lost: " + ", ".join(parts)


def pre_trigger_span(table, bad=None):
    """``(lowest, highest)`` trigger index where every intact row of a recording's frame table
    (``bad``: its damaged rows) counts back from a trigger that never came (a triggered recording
    stopped while it waited: the event is not in it); None otherwise (a trigger frame, frames after
    it, no trigger index). What ``process``'s note and the Replay tab both say."""
    if table is None or "trigger_index" not in (table.dtype.names or ()) or not len(table):
        return None
    t = np.asarray(table["trigger_index"], dtype=np.int64)
    t = t[~bad] if bad is not None else t
    if not len(t) or np.any(t >= 0) or np.any(t == np.iinfo(np.int64).min):
        return None
    return int(t.min()), int(t.max())


def parse_frame_range(text: str) -> slice:
    """``START:STOP:STEP`` (Python slice syntax, each part optional, negatives count
    from the end) as a :class:`slice`; a single number ``K`` means frame K alone.

    Raises
    ------
    ImageReadError
        Not of that form, or a step that is not positive.
    """
    parts = str(text).strip().split(":")
    try:
        if len(parts) == 1:
            k = int(parts[0])
            return slice(k, k + 1 if k != -1 else None, 1)
        if len(parts) > 3:
            raise ValueError
        values = [int(t) if t.strip() else None for t in parts] + [None] * (3 - len(parts))
    except ValueError:
        raise ImageReadError(
            f"frame range {text!r} is not START:STOP:STEP (whole numbers, each optional, "
            f"e.g. 0:20 or 100::2)") from None
    start, stop, step = values
    if step is not None and step < 1:
        raise ImageReadError(f"the step of frame range {text!r} must be >= 1; got {step}")
    return slice(start, stop, step)


def average_frames(path, frames: slice, pattern: str = "checkerboard") -> np.ndarray:
    """Mean of the frames ``frames`` of one input (a file, or a folder / glob of
    images counted as one sequence), float32 (an averaged reference), of the frames
    that agree with the first: :class:`processing.reference_average.ReferenceAverager`,
    as the live window's Ctrl+R (``pattern``: "checkerboard" compares carrier phases,
    "dots" grey levels). Frames of moving water averaged made a reference of a surface
    that was never there (by-hand trial of 7 Dec 2026: waves of 1 rad, heights 100-116 %
    off, exit 0).

    Raises
    ------
    ImageReadError
        Unreadable file, or a range that selects no frame.
    processing.reference_average.WaterMovingError
        More than a fifth of the frames disagree with the first: the water moved.
    """
    from processing.reference_average import ReferenceAverager, first_frame_carriers

    p = expand_inputs([path])
    n = count_frames(p)
    picked = range(n)[frames]
    if len(picked) == 0:
        raise ImageReadError(
            f"the reference frames {frames.start}:{frames.stop}:{frames.step or 1} select no frame "
            f"of the {n} in {str(path)!r}; frames count from 0")
    averager, fed = None, []
    for item in iter_frames(p, first=picked.start, last=picked[-1], step=picked.step):
        if averager is None:
            averager = ReferenceAverager(first_frame_carriers(item.image, pattern),
                                         remedy=f"give --reference-frames of {str(path)!r} where it is still "
                                                f"(the frames before the event)")
        averager.add(item.image)  # (the averager sums in float64 itself)
        fed.append(item.sequence_index)
    reference, report = averager.result(frame_numbers=fed)
    (log.warning if report.n_averaged < report.n_frames else log.info)(
        "reference: frames %d..%d of %s: %s", picked[0], picked[-1], path, report.text())
    return reference


def _local_range(seq: int, n: int, first: int, last: int | None, step: int) -> range:
    """Indices within a file of ``n`` frames starting at sequence index ``seq``
    that the selection ``first..last`` (inclusive) every ``step`` picks."""
    stop = n if last is None else max(0, min(n, last - seq + 1))
    i0 = max(0, first - seq)
    r = (seq + i0 - first) % step
    if r:
        i0 += step - r
    return range(i0, max(i0, stop), step)


def write_image(path, image: np.ndarray) -> Path:
    """Write one grey image losslessly; 8-bit as PNG/BMP/TIFF, 9-16 bit as PNG or TIFF.

    Parameters
    ----------
    path : path-like
        Suffix selects the format (``.png``, ``.bmp``, ``.tif``/``.tiff``).
    image : numpy.ndarray
        ``(rows, cols)`` uint8 or uint16 (float32 only to TIFF).

    Returns
    -------
    pathlib.Path
    """
    p = Path(path)
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"write_image expects a (rows, cols) array; got shape {image.shape}")
    suffix = p.suffix.lower()
    if suffix in TIFF_SUFFIXES:
        import tifffile

        tifffile.imwrite(p, image, photometric="minisblack")
        return p
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{suffix} stores uint8/uint16 only; got {image.dtype}: use .tif")
    if suffix == ".bmp" and image.dtype != np.uint8:
        raise ValueError("BMP stores 8-bit images only; use .png or .tif for 16 bit")
    import cv2

    ok, buf = cv2.imencode(suffix, image)
    if not ok:
        raise OSError(f"OpenCV could not encode {p} as {suffix}")
    buf.tofile(p)
    return p
