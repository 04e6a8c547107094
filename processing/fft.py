"""FFTW plans for the demodulation: float32/complex64, multithreaded, built once.

The numerics need three kinds of transforms, each for one fixed shape per
reference: a real-to-complex forward transform of the full frame (as its two
1-D passes, the second optionally on a band of low column frequencies only:
all that the carrier windows read), small complex inverse transforms of the
windows cut around each carrier (decimated grid) and, optionally, full-size
complex inverse transforms (full grid).

:class:`FFTPlanner` builds a plan the first time a (kind, shape) is asked for
and keeps it; planning happens on scratch arrays, or on the plan's own arrays
with their data copied aside and put back (FFTW_MEASURE overwrites the arrays
it plans on: the real transform's column passes, planned when first asked
for), so callers never lose data to the planner.  One planner belongs
to one :class:`~processing.reconstruct.Reconstructor`: plans own their
arrays, so two threads must not share a planner.

FFTW's *wisdom* (what the planner measured) is global to the process;
:func:`export_wisdom` packs it into one ``bytes`` object that the app stores
on disk, and :func:`import_wisdom` loads it back, so that FFTW_MEASURE plans
cost milliseconds on the next start.  Processing never touches files.
"""

from __future__ import annotations

import struct
import sys
import threading

import numpy as np


def _import_pyfftw():
    """Import pyfftw without its Dask interface.

    ``import pyfftw`` imports ``pyfftw.interfaces``, which imports ``dask.array``
    (about 0.85 s of CPU, more than numpy and pyfftw together) whenever Dask is
    installed, only to offer ``pyfftw.interfaces.dask_fft``, which tirdeflect
    never uses.  Every process that reconstructs (each CLI run, each batch worker,
    the live window's reconstruction process) paid it at start.  While pyfftw is
    imported, ``dask`` is marked as not importable (``sys.modules[name] = None``
    makes an import raise ImportError, which pyfftw catches); the mark is taken
    away at once, so that ``--dask`` imports Dask as usual afterwards.  Where
    Dask is already imported this changes nothing.
    """
    if "dask" in sys.modules or "pyfftw" in sys.modules:
        import pyfftw as module
        return module
    sys.modules["dask"] = None
    try:
        import pyfftw as module
    finally:
        if sys.modules.get("dask", 0) is None:
            del sys.modules["dask"]
    return module


pyfftw = _import_pyfftw()

__all__ = [
    "FFTPlanner",
    "PLANNER_EFFORTS",
    "export_wisdom",
    "import_wisdom",
]

#: Planner efforts FFTW accepts, cheapest first.  Tests use FFTW_ESTIMATE
#: (no measuring), the app FFTW_MEASURE together with cached wisdom.
PLANNER_EFFORTS = ("FFTW_ESTIMATE", "FFTW_MEASURE", "FFTW_PATIENT", "FFTW_EXHAUSTIVE")

_WISDOM_MAGIC = b"TIRDFFTW1\n"
_wisdom_lock = threading.Lock()


def export_wisdom() -> bytes:
    """Return FFTW's accumulated wisdom (all precisions) as one bytes object.

    Returns
    -------
    bytes
        Opaque blob for :func:`import_wisdom`; store it as a binary file.
    """
    with _wisdom_lock:
        parts = pyfftw.export_wisdom()
    out = [_WISDOM_MAGIC, struct.pack("<I", len(parts))]
    for part in parts:
        out.append(struct.pack("<Q", len(part)))
        out.append(bytes(part))
    return b"".join(out)


def import_wisdom(wisdom: bytes) -> bool:
    """Load wisdom produced by :func:`export_wisdom` (possibly by another run).

    Parameters
    ----------
    wisdom : bytes
        Blob from :func:`export_wisdom`.

    Returns
    -------
    bool
        True if FFTW accepted the wisdom of every precision.  False means the
        blob came from another FFTW build: plans will simply be measured
        again (slower start, same results).

    Raises
    ------
    ValueError
        If ``wisdom`` is not a tirdeflect wisdom blob (wrong file?).
    """
    if not isinstance(wisdom, (bytes, bytearray, memoryview)):
        raise ValueError(
            f"FFTW wisdom must be bytes from export_wisdom(); got {type(wisdom).__name__}"
        )
    blob = bytes(wisdom)
    if not blob.startswith(_WISDOM_MAGIC):
        raise ValueError(
            "FFTW wisdom blob does not start with the tirdeflect header "
            f"(first bytes {blob[:12]!r}); delete the wisdom file, it is rebuilt on the next run"
        )
    pos = len(_WISDOM_MAGIC)
    try:
        (count,) = struct.unpack_from("<I", blob, pos)
        pos += 4
        parts = []
        for _ in range(count):
            (length,) = struct.unpack_from("<Q", blob, pos)
            pos += 8
            if pos + length > len(blob):
                raise struct.error("truncated")
            parts.append(blob[pos:pos + length])
            pos += length
    except struct.error:
        raise ValueError(
            f"FFTW wisdom blob is truncated ({len(blob)} bytes); delete the wisdom "
            "file, it is rebuilt on the next run"
        ) from None
    with _wisdom_lock:
        ok = pyfftw.import_wisdom(tuple(parts))
    return bool(np.all(ok))


class FFTPlanner:
    """Cache of FFTW plans (float32/complex64) for fixed shapes.

    Parameters
    ----------
    threads : int, optional
        Threads FFTW may use per transform (default 2).
    planner_effort : str, optional
        One of :data:`PLANNER_EFFORTS`.  ``"FFTW_ESTIMATE"`` plans instantly
        (tests); ``"FFTW_MEASURE"`` (default) times candidate algorithms once
        per shape, which pays off for live processing, especially with wisdom
        imported from an earlier run.

    Notes
    -----
    Each plan owns aligned input and output arrays.  The methods copy the
    caller's data into the plan's input array and return the plan's output
    array, which the next call of the same plan overwrites: copy it if it must
    live longer.
    """

    def __init__(self, *, threads: int = 2, planner_effort: str = "FFTW_MEASURE"):
        if planner_effort not in PLANNER_EFFORTS:
            raise ValueError(
                f"planner_effort must be one of {PLANNER_EFFORTS}; got {planner_effort!r}"
            )
        threads = int(threads)
        if threads < 1:
            raise ValueError(f"threads must be >= 1; got {threads}")
        self.threads = threads
        self.planner_effort = planner_effort
        self._plans = {}

    def _plan(self, kind, shape):
        key = (kind, tuple(int(s) for s in shape))
        plan = self._plans.get(key)
        if plan is not None:
            return plan
        rows, cols = key[1][-2:]
        lead = key[1][:-2]  # batch dimensions: transforms along the last two axes
        # Small transforms gain nothing from threads (and lose to the overhead,
        # badly so on a loaded machine).
        threads = self.threads if rows * cols >= 384 * 384 else 1
        if kind == "rfft2":
            plan = _RealPlan(lead + (rows, cols), self.planner_effort, threads)
        elif kind in ("fft2", "ifft2"):
            src = pyfftw.empty_aligned(lead + (rows, cols), dtype="complex64")
            dst = pyfftw.empty_aligned(lead + (rows, cols), dtype="complex64")
            direction = "FFTW_FORWARD" if kind == "fft2" else "FFTW_BACKWARD"
            with _wisdom_lock:
                plan = pyfftw.FFTW(
                    src, dst, axes=(-2, -1), direction=direction,
                    flags=(self.planner_effort, "FFTW_DESTROY_INPUT"), threads=threads,
                )
        else:  # pragma: no cover - internal misuse
            raise ValueError(f"unknown transform kind {kind!r}")
        self._plans[key] = plan
        return plan

    def prepare(self, kind: str, shape, columns=None) -> None:
        """Build (plan) a transform ahead of time so that no call pays for it.

        Parameters
        ----------
        kind : {"rfft2", "fft2", "ifft2"}
        shape : tuple of int
            ``(rows, cols)`` of the real input (rfft2) or of the complex array;
            leading dimensions make a batch of transforms over the last two axes.
        columns : int, optional
            rfft2 only: plan the transform of the first ``columns`` output
            columns alone (see :meth:`execute`).
        """
        _columns_of(kind, columns)
        plan = self._plan(kind, shape)
        if kind == "rfft2":
            plan.columns_plan(columns)

    def input_array(self, kind: str, shape) -> np.ndarray:
        """The plan's own input array: write into it, then call ``execute(kind, shape)``.

        Saves one copy per transform on the live path.
        """
        return self._plan(kind, shape).input_array

    def execute(self, kind: str, shape, normalise: bool = True, columns=None) -> np.ndarray:
        """Run the plan on whatever its input array holds; return its output array.

        Inverse transforms are normalised by ``1 / (rows * cols)`` unless
        ``normalise`` is False (callers that scale anyway save a pass).
        ``columns`` (rfft2 only): only the output's first ``columns`` columns
        (frequencies ``0 .. columns - 1`` cycles per width) are transformed
        along the rows axis; the others hold the row transforms alone, not
        the spectrum (for callers that read only those columns: the carrier
        windows).
        """
        _columns_of(kind, columns)
        plan = self._plan(kind, shape)
        if kind == "rfft2":
            plan.execute(columns)
        else:
            plan.execute()
        out = plan.output_array
        if kind == "ifft2" and normalise:
            out *= np.float32(1.0 / (out.shape[-2] * out.shape[-1]))
        return out

    def rfft2(self, image: np.ndarray) -> np.ndarray:
        """Forward real FFT of a 2-D float image.

        Parameters
        ----------
        image : ndarray, shape (rows, cols)
            Any real dtype; converted to float32.

        Returns
        -------
        ndarray, complex64, shape (rows, cols // 2 + 1)
            Unnormalised spectrum (the plan's output array).
        """
        shape = image.shape
        self.input_array("rfft2", shape)[...] = image
        return self.execute("rfft2", shape)

    def fft2(self, array: np.ndarray) -> np.ndarray:
        """Forward complex FFT (complex64), unnormalised; the plan's output array."""
        shape = array.shape
        self.input_array("fft2", shape)[...] = array
        return self.execute("fft2", shape)

    def ifft2(self, spectrum: np.ndarray) -> np.ndarray:
        """Inverse complex FFT (complex64), normalised; the plan's output array."""
        shape = spectrum.shape
        self.input_array("ifft2", shape)[...] = spectrum
        return self.execute("ifft2", shape)


def _columns_of(kind, columns):
    """Refuse ``columns`` (a band of the real transform's output columns) for any other transform."""
    if columns is not None and kind != "rfft2":
        raise ValueError(f"columns applies to rfft2 only, not {kind!r}")


class _RealPlan:
    """The forward real 2-D FFT as its two passes: real-to-complex along each
    row, then complex along each column of the half spectrum, in place.

    Two passes give FFTW's own 2-D plan bit for bit (both split the transform
    so; checked with FFTW_MEASURE at 512^2-2048^2, 1 and 2 threads) and as
    fast, and they let a caller that reads a band of low column frequencies
    only (the carrier windows: about a quarter of the 513 columns of a
    1024^2 frame) skip the other columns' pass: 2.6 -> 1.7 ms at 1024^2 on one
    thread (1.6 -> 1.15 on two), 7.8 against 13.3 ms at 2048^2.  In place
    (the real input is a padded view of the complex output): half the
    memory a frame streams through, measured 0.71 -> 0.63 ms for conversion
    + FFT at 512^2 when other work evicted the caches.
    """

    def __init__(self, shape, planner_effort, threads):
        cols = shape[-1]
        self.output_array = pyfftw.empty_aligned(shape[:-1] + (cols // 2 + 1,), dtype="complex64")
        self.input_array = self.output_array.view(np.float32)[..., :cols]
        self._flags = (planner_effort, "FFTW_DESTROY_INPUT")
        self._threads = threads
        with _wisdom_lock:
            self._rows = pyfftw.FFTW(self.input_array, self.output_array, axes=(-1,),
                                     direction="FFTW_FORWARD", flags=self._flags, threads=threads)
        self._columns = {}  # the column passes, planned when first asked for (batch never takes all)

    def columns_plan(self, columns=None):
        """The pass along the rows axis of the first ``columns`` columns (None: all)."""
        half = self.output_array.shape[-1]
        n = half if columns is None else int(columns)
        if not 1 <= n <= half:
            raise ValueError(f"columns must be in 1..{half}; got {columns}")
        plan = self._columns.get(n)
        if plan is None:
            band = self.output_array[..., :n]
            kept = band.copy()  # planning (FFTW_MEASURE) overwrites the array it plans on
            with _wisdom_lock:
                plan = pyfftw.FFTW(band, band, axes=(-2,), direction="FFTW_FORWARD",
                                   flags=self._flags, threads=self._threads)
            band[...] = kept
            self._columns[n] = plan
        return plan

    def execute(self, columns=None):
        self._rows.execute()
        self.columns_plan(columns).execute()
