"""How many frames a TIFF stack declares, and which of them a cut stack still holds.

Used by :mod:`app.files.imageio` (the one reader); nothing else needs it.

A multi-page TIFF whose copy or recording was interrupted loses its end. ImageJ
and tifffile write every image directory (IFD) but the first *after* all the
pixels, so a cut anywhere in the pixels loses every directory but page 0: tifffile
then lists one page and only logs ``invalid page offset`` (a 4-frame stack read as
1 frame, 3 frames lost without a word). A physicist must never lose a frame without
being told, so the count of frames is what the file *declares*:

- ImageJ's description (``images=``, or ``channels x slices x frames``, read as
  tifffile reads an ImageJ series),
- tifffile's shaped description (``{"shape": [4, 256, 256]}``: the pages of the
  series that page 0 starts),
- the chain of image directories: the last whole one pointing past the end of the
  file declares at least one page more,

whichever is the most, never fewer than the pages listed. The frames past the
pages whose directories survived are read from the pixels where the file stores
them back to back (ImageJ always does; tifffile does by default), uncompressed,
as tifffile itself reads such a series from page 0; every frame whose pixels are
not (all) in the file is a :class:`ImageReadError` that says the file is truncated,
names the file and the frame, and says to copy the file again.

tifffile's own log lines (``ERROR: <tifffile.TiffPages @8> invalid page offset
524640``) are caught while the reader works (:func:`quiet_tifffile`): what they
mean is said in the reader's messages instead.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import re
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from app.files.formats import ImageReadError

__all__ = ["StackExtent", "quiet_tifffile", "stack_extent", "frame_beyond_pages", "header_cut"]

#: the directories a chain may hold before it is taken for a loop (a damaged file)
_MAX_PAGES = 10_000_000


class _Capture(logging.Filter):
    """On tifffile's logger: while a thread is inside :func:`quiet_tifffile`, its
    records are kept in that thread's list instead of reaching the user's log."""

    def __init__(self):
        super().__init__()
        self.local = threading.local()

    def filter(self, record: logging.LogRecord) -> bool:
        said = getattr(self.local, "said", None)
        if said is None:
            return True  # not one of the reader's calls (e.g. a write): as tifffile logs it
        said.append(record.getMessage())
        return False


_CAPTURE = _Capture()
_INSTALL = threading.Lock()


@contextlib.contextmanager
def quiet_tifffile() -> Iterator[list]:
    """``with quiet_tifffile() as said:`` tifffile's log records of this thread, kept in
    ``said`` (a list of str) instead of logged; nested uses share the outer list."""
    logger = logging.getLogger("tifffile")
    with _INSTALL:
        if _CAPTURE not in logger.filters:
            logger.addFilter(_CAPTURE)
    outer = getattr(_CAPTURE.local, "said", None)
    said = outer if outer is not None else []
    _CAPTURE.local.said = said
    try:
        yield said
    finally:
        _CAPTURE.local.said = outer


@dataclass(frozen=True)
class StackExtent:
    """What a TIFF file holds against what it declares.

    Attributes
    ----------
    pages : int
        Pages whose image directory is whole in the file: read through tifffile.
    declared : int
        Frames the file declares (>= ``pages``; see the module doc).
    declared_by : str
        Which part of the file declares more frames than ``pages``, said before "says
        it holds N frames": e.g. ``"its ImageJ description (images=4)"``; "" when
        the file declares no more, or only its cut chain of image directories does
        (at least one page more: the one its last whole directory points to).
    size : int
        Length of the file in bytes.
    cut : str
        Why the chain of image directories ends early ("" when it ends as written).
    contiguous : tuple of (int, int) or None
        ``(offset, nbytes)``: frame ``k``'s pixels are the ``nbytes`` bytes at
        ``offset + k * nbytes`` (uncompressed, back to back), where the file says
        its frames are stored so and the pages listed agree; None otherwise.
    """

    pages: int
    declared: int
    declared_by: str
    size: int
    cut: str = ""
    contiguous: tuple | None = None


def _layout(head: bytes):
    """``(first IFD offset field's position, offset format, tag-count format, tag size)``
    of a classic or BigTIFF header ``head`` (its first 16 bytes), or None."""
    if len(head) < 8 or head[:2] not in (b"II", b"MM"):
        return None
    order = "<" if head[:2] == b"II" else ">"
    magic = struct.unpack(order + "H", head[2:4])[0]
    if magic == 42:
        return 4, order + "I", order + "H", 12
    if magic == 43:
        return 8, order + "Q", order + "Q", 20
    return None


def _chain(p: Path, size: int) -> tuple:
    """``(whole, cut)``: the image directories from the header on that lie whole in the
    file ``p`` of ``size`` bytes, and why the chain stops early ("" when its last
    directory ends it, or the file is damaged in a way that is no cut)."""
    with open(p, "rb") as fh:
        layout = _layout(fh.read(16))
        if layout is None:
            return 0, ""
        at, offset_format, count_format, tag_size = layout
        offset_size, count_size = struct.calcsize(offset_format), struct.calcsize(count_format)
        fh.seek(at)
        head = fh.read(offset_size)
        if len(head) < offset_size:
            return 0, f"it ends at byte {size}, inside its header"
        offset = struct.unpack(offset_format, head)[0]
        whole, seen = 0, set()
        while offset and whole < _MAX_PAGES:
            what = "its first image directory" if whole == 0 else f"the image directory of page {whole}"
            if offset in seen:
                return whole, ""
            seen.add(offset)
            fh.seek(offset)
            raw = fh.read(count_size) if offset < size else b""
            if len(raw) < count_size:
                return whole, f"{what} starts at byte {offset}"
            end = offset + count_size + struct.unpack(count_format, raw)[0] * tag_size + offset_size
            if end > size:
                return whole, f"{what} runs from byte {offset} to byte {end}"
            fh.seek(end - offset_size)
            offset = struct.unpack(offset_format, fh.read(offset_size))[0]
            whole += 1
    return whole, ""


def _ends_at(p: Path, size: int, offset: int) -> bool:
    """Whether the image directory at byte ``offset`` of the TIFF ``p`` is whole and
    ends the chain (its pointer to a next directory is 0): a file tifffile read to
    its last page."""
    with open(p, "rb") as fh:
        layout = _layout(fh.read(16))
        if layout is None:
            return False
        _, offset_format, count_format, tag_size = layout
        offset_size, count_size = struct.calcsize(offset_format), struct.calcsize(count_format)
        fh.seek(offset)
        raw = fh.read(count_size)
        if len(raw) < count_size:
            return False
        end = offset + count_size + struct.unpack(count_format, raw)[0] * tag_size + offset_size
        if end > size:
            return False
        fh.seek(end - offset_size)
        return struct.unpack(offset_format, fh.read(offset_size))[0] == 0


def _read_to_the_end(tif, p: Path, size: int, listed: int) -> bool:
    """Whether tifffile's ``listed`` pages end where the file's chain of image
    directories ends (checked on the last one only: a few bytes)."""
    try:
        with quiet_tifffile():
            return listed > 0 and _ends_at(p, size, int(tif.pages[listed - 1].offset))
    except Exception:  # noqa: BLE001 -- a last page that does not parse: walk the chain
        return False


def header_cut(p: Path) -> str:
    """Why the TIFF ``p`` (that tifffile cannot open, or finds no page in) is cut short
    before its first image directory is whole (e.g. "it is 100 bytes long but its first image directory
    starts at byte 131328 ..."), or "" when that is not why."""
    size = p.stat().st_size
    whole, cut = _chain(p, size)
    if whole or not cut:
        return ""
    return f"it is {size} bytes long but {cut} (an interrupted copy or recording)"


def _shaped_count(page) -> tuple:
    """Pages that tifffile's shaped description on ``page`` declares for its series, and
    the shape it gives, or (0, None)."""
    text = getattr(page, "shaped_description", None)
    if not text:
        return 0, None
    try:
        if text.lstrip().startswith("{"):
            shape = [int(v) for v in json.loads(text)["shape"]]
        else:  # tifffile before 2019: 'shape=(4, 256, 256)'
            m = re.search(r"shape=\(([\d,\s]*)\)", text)
            shape = [int(v) for v in m.group(1).replace(" ", "").split(",") if v] if m else []
    except (ValueError, KeyError, TypeError):
        return 0, None
    per_page = math.prod(int(s) for s in page.shape)
    total = math.prod(shape) if shape else 0
    if per_page <= 0 or total <= 0 or total % per_page:
        return 0, None
    return total // per_page, shape


def _imagej_count(tif, page) -> tuple:
    """Images (pages) that an ImageJ description declares, counted as tifffile counts an
    ImageJ series, and the words that say so; (0, "") if the file is no ImageJ file."""
    try:
        meta = tif.imagej_metadata if tif.is_imagej else None
    except Exception:  # noqa: BLE001 -- a damaged description declares nothing
        meta = None
    if not meta:
        return 0, ""
    try:
        frames, slices = int(meta.get("frames", 1)), int(meta.get("slices", 1))
        channels, images = int(meta.get("channels", 1)), int(meta.get("images", 1))
        separate, contig = int(page.shaped[0]), int(page.shaped[4])
    except (TypeError, ValueError, AttributeError, IndexError):
        return 0, ""
    if min(frames, slices, channels, images) < 1:
        return 0, ""
    if channels == 1 or (separate > 1 and separate == channels):
        count = frames * slices  # colour samples declared as channels
    elif images == frames * slices and contig == channels:
        count = images
    else:
        count = frames * slices * channels
    if count == images:
        return count, f"its ImageJ description (images={images})"
    return count, f"its ImageJ description ({frames} frames x {slices} slices x {channels} channels)"


def _contiguous(pages, page0, whole: int, series: int) -> tuple | None:
    """``(offset, nbytes)`` of page 0's pixels where the series of ``series`` pages it
    starts is stored back to back, uncompressed, and the listed pages agree; else None."""
    try:
        if not page0.is_final or page0.nbytes <= 0:
            return None
        offset, nbytes = int(page0.dataoffsets[0]), int(page0.nbytes)
        for k in range(1, min(whole, series)):
            if int(pages[k].dataoffsets[0]) != offset + k * nbytes:
                return None
    except Exception:  # noqa: BLE001 -- a page that does not parse: no layout to trust
        return None
    return offset, nbytes


def stack_extent(tif, p: Path, listed: int, complained: bool) -> StackExtent:
    """What the TIFF ``tif`` (open on the file ``p``) holds and declares.

    ``listed`` is the number of pages tifffile found, ``complained`` whether it logged
    a problem while finding them. Where it did, or its last page does not end the
    chain, the chain of image directories is walked here (plain reads of a few bytes
    a page) to tell a cut file from a damaged one.
    """
    size = p.stat().st_size
    whole, cut = listed, ""
    if complained or not _read_to_the_end(tif, p, size, listed):
        whole, cut = _chain(p, size)
        whole = min(whole, listed)
    if whole == 0:
        return StackExtent(0, 0, "", size, cut)
    pages = tif.pages
    page0 = pages.first if hasattr(pages, "first") else pages[0]
    declared, declared_by, series = whole, "", 0
    count, words = _imagej_count(tif, page0)
    if not count:
        count, shape = _shaped_count(page0)
        words = f"its tifffile description (shape {shape})" if count else ""
    if count > declared:
        declared, declared_by, series = count, words, count
    if cut and declared <= whole:
        declared, declared_by = whole + 1, ""  # at least the page the chain points to
    contiguous = _contiguous(pages, page0, whole, series) if series > whole else None
    return StackExtent(whole, declared, declared_by, size, cut, contiguous)


def frame_beyond_pages(p: Path, extent: StackExtent, k: int, page0, byteorder: str) -> np.ndarray:
    """Frame ``k`` (``extent.pages <= k < extent.declared``) of the TIFF ``p``, read from
    its back-to-back pixels, in page 0's shape and dtype.

    Raises
    ------
    ImageReadError
        Its pixels are not (all) in the file, or cannot be found there: the file is
        truncated (an interrupted copy or recording).
    """
    if extent.contiguous is not None:
        offset, nbytes = extent.contiguous
        start = offset + k * nbytes
        if start + nbytes <= extent.size:
            dtype = np.dtype(page0.dtype).newbyteorder(byteorder)
            count = nbytes // dtype.itemsize
            arr = np.fromfile(p, dtype=dtype, count=count, offset=start)
            if arr.size == count:
                return arr.reshape(page0.shape).astype(dtype.newbyteorder("="))
        reason = f"frame {k}'s pixels would run from byte {start} to byte {start + nbytes}"
    elif extent.cut:
        reason = f"{extent.cut}, so page {extent.pages} and every page after it are lost"
    else:
        raise _not_found(p, extent, k)
    holds = f"{extent.declared_by} says it holds {extent.declared} frames, but " if extent.declared_by else ""
    raise ImageReadError(
        f"frame {k} of {str(p)!r} is missing: the file is truncated: {holds}it is {extent.size} bytes "
        f"long and {reason} (an interrupted copy or recording); copy the file again from its source")


def plane_of_page(p: Path, page, k: int, planes: int, byteorder: str) -> np.ndarray:
    """Plane ``k`` of ``page``, a page of ``planes`` separate planes (one grey frame each: see
    ``imageio._planes_of_a_stack``), read alone where its strips are stored uncompressed, so that
    the planes an interrupted copy left whole stay readable (tifffile reads the page's planes together:
    a cut in the last plane lost every frame of the file with a ValueError, by-hand trial of 7 Dec 2026).

    Raises
    ------
    ImageReadError
        The plane's pixels are not all in the file (it is truncated), or the page cannot be decoded.
    """
    offsets, counts = list(page.dataoffsets), list(page.databytecounts)
    per = len(offsets) // planes if planes else 0
    dtype = np.dtype(page.dtype).newbyteorder(byteorder)
    rows, cols = int(page.imagelength), int(page.imagewidth)
    if int(page.compression) != 1 or per * planes != len(offsets) or int(page.bitspersample) != 8 * dtype.itemsize:
        try:
            return np.asarray(page.asarray())[k]
        except Exception as exc:  # noqa: BLE001 - tifffile's ValueError of a short read, or a codec's
            raise ImageReadError(f"frame {k} of {str(p)!r} cannot be read ({exc}); the file may be truncated "
                                 f"(an interrupted copy): copy it again from its source") from None
    need = rows * cols * dtype.itemsize
    data = bytearray()
    with open(p, "rb") as fh:
        for offset, count in zip(offsets[k * per:(k + 1) * per], counts[k * per:(k + 1) * per]):
            fh.seek(int(offset))
            data += fh.read(int(count))
    if len(data) < need:
        raise ImageReadError(
            f"frame {k} of {str(p)!r} is missing: the file is truncated: it is {p.stat().st_size} bytes long and "
            f"frame {k} (plane {k} of its one page) is cut off (an interrupted copy or recording); copy the file "
            f"again from its source")
    return np.frombuffer(bytes(data[:need]), dtype).reshape(rows, cols).astype(dtype.newbyteorder("="))


def _not_found(p: Path, extent: StackExtent, k: int) -> ImageReadError:
    """The error for a declared frame past the last page of a file whose directories end
    as written and whose pixels are not stored back to back: it cannot be found."""
    return ImageReadError(
        f"frame {k} of {str(p)!r} is missing: {extent.declared_by} says the file holds "
        f"{extent.declared} frames, but its image directories end after {extent.pages} page(s) and "
        f"its pixels are not stored back to back, so frame {k} cannot be found (pages removed after "
        f"it was written?); copy the file again from its source")
