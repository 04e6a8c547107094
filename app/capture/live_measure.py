"""One live frame measured: the function that the processing worker runs in its thread or in its
worker process (:mod:`app.capture.worker`, :mod:`app.capture.live_process`), and what it takes and gives.

No Qt, no threads; everything here is picklable.
"""

from __future__ import annotations

import dataclasses
import time
import traceback
from typing import Optional

import numpy as np

from processing.banding import bands_of, evened_frame

__all__ = ["LiveJob", "Measured", "WorkerStopped", "measure_live", "error_message", "thread_clock"]


@dataclasses.dataclass(frozen=True)
class LiveJob:
    """What the worker asks of one frame (picklable: it is sent to the worker process).

    ``grid``: "decimated" or "full"; ``reset_series``: start the temporal unwrapping anew
    (a new reconstructor or grid); ``alignment``: also compute the alignment metrics and spectrum;
    ``bands``: judge the frame's bands of light along the rows against the reference
    (:func:`processing.banding.bands_of`) and even them out before measuring.
    """

    grid: str = "decimated"
    reset_series: bool = False
    alignment: bool = False
    bands: bool = False


@dataclasses.dataclass
class Measured:
    """What :func:`measure_live` gives for one frame (wherever it ran).

    ``result`` (:class:`processing.Result`) or ``error`` (one line); ``alignment``/``spectrum``
    when the job asked for them; ``processing_s`` wall and ``cpu_s`` CPU time of the reconstruction,
    ``queued_s`` the part of its wall time the thread was runnable but waiting for a core (Linux
    schedstat; 0 elsewhere): ``processing_s - cpu_s - queued_s`` is time it was blocked, above all
    waiting for its process's GIL,
    ``alignment_s`` wall time of alignment + spectrum, seconds; ``traceback_text``: the traceback of
    an unexpected error (not a :class:`ValueError`), for the log; ``light_bands``: the frame's
    :class:`processing.banding.LightBands` where the job asked and the reconstructor keeps the
    reference's row profile (evened out before measuring where :attr:`~processing.banding.LightBands.evened`),
    else None.
    """

    result: object = None
    error: Optional[str] = None
    alignment: Optional[dict] = None
    spectrum: object = None
    processing_s: float = 0.0
    cpu_s: float = 0.0
    queued_s: float = 0.0
    alignment_s: float = 0.0
    traceback_text: Optional[str] = None
    light_bands: object = None


def measure_live(reconstructor, image: np.ndarray, job: LiveJob) -> Measured:
    """Reconstruct one frame for the live view: the one function the worker thread and the
    worker process both run.

    Parameters
    ----------
    reconstructor : processing.Reconstructor
    image : ndarray, shape (rows, cols)
        The camera frame.
    job : LiveJob

    Returns
    -------
    Measured
        A processing error becomes ``error`` (never raised), an alignment error ``{"error": ...}``.
    """
    out = Measured()
    t0, (c0, q0) = time.perf_counter(), thread_clock()
    try:
        if job.reset_series and hasattr(reconstructor, "reset_series"):
            reconstructor.reset_series()
        if job.bands:  # as the batch does (app.batch.frame_status.measure_frame): evened, then measured
            out.light_bands = bands_of(reconstructor, image)
        out.result = reconstructor(evened_frame(image, out.light_bands), grid=job.grid)
    except Exception as exc:  # TirdeflectError: show it, keep going
        out.error = error_message(exc)
        if not isinstance(exc, ValueError):
            out.traceback_text = traceback.format_exc()
    c1, q1 = thread_clock()
    out.processing_s, out.cpu_s, out.queued_s = time.perf_counter() - t0, c1 - c0, q1 - q0
    if job.alignment and hasattr(reconstructor, "alignment"):
        t0 = time.perf_counter()
        try:
            out.alignment = reconstructor.alignment(image)
            out.spectrum = reconstructor.spectrum(image) if hasattr(reconstructor, "spectrum") else None
        except Exception as exc:
            out.alignment = {"error": error_message(exc)}
        out.alignment_s = time.perf_counter() - t0
    return out


def thread_clock() -> tuple:
    """``(cpu_s, queued_s)`` of the calling thread so far: seconds it ran on a core, and seconds it was
    runnable but waiting for one (Linux ``/proc/thread-self/schedstat``; elsewhere 0 for the second)."""
    try:
        with open("/proc/thread-self/schedstat", "rb") as f:
            ran_ns, waited_ns = f.read().split()[:2]
        return int(ran_ns) / 1e9, int(waited_ns) / 1e9
    except (OSError, ValueError):
        return time.thread_time(), 0.0


class WorkerStopped(Exception):
    """The worker was stopped while its process measured a frame (nothing to publish)."""


def error_message(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    return text if isinstance(exc, ValueError) else f"{type(exc).__name__}: {text}"
