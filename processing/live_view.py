"""What the live Alignment tab shows of a frame against a Reconstructor's
reference: :class:`LiveView` (alignment metrics and the display spectrum of
one FFT, :mod:`processing.alignment`), and :func:`saturation_pct`."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["LiveView", "saturation_pct", "SATURATION_MAX_PCT", "reference_saturation"]


#: Saturated pixels (% of a frame) above which it is not ready (the Alignment tab) and is named in
#: a batch run's summary: clipped grey levels flatten the pattern's bright squares. Ray-traced 12-bit
#: frames over-exposed until 32 / 35 / 40 / 45 % of pixels clip: 4 um bump 0.075 -> 0.095 / 0.145 /
#: 0.246 / 0.503 % rms height error, narrow bump 0.185 -> 0.225 / 0.376 / 0.650 / 1.325 % (5 Dec 2026).
SATURATION_MAX_PCT = 1.0


def saturation_pct(frame) -> float:
    """Percentage of pixels at the top code of the frame's bit depth.

    For integer frames the bit depth is the smallest that holds the frame's
    maximum (a 10-bit camera in uint16 saturates at 1023); float frames
    saturate at 1.0 or at their maximum if above 1.
    """
    a = np.asarray(frame)
    top = float(a.max()) if a.size else 0.0
    if a.dtype.kind in "ui":
        bits = max(1, int(math.ceil(math.log2(top + 1)))) if top > 0 else 1
        level = 2 ** bits - 1
    else:
        level = 1.0 if top <= 1.0 else top
    return float(100.0 * np.count_nonzero(a >= level) / max(a.size, 1))


def reference_saturation(reference, *, averaged_counts: bool = False):
    """``(percent, sentence)`` where more than :data:`SATURATION_MAX_PCT` of the reference's pixels
    are saturated (:func:`saturation_pct`; every frame is measured against its clipped squares), else
    None: what ``tirdeflect process`` warns of and the window's reference label says.  Measured
    (6 Dec 2026, ``tirdeflect simulate`` 512^2, 12 bit): the reference 1.3x as bright, 42 % clipped,
    the bump's rms height error 0.05 -> 0.18 %, the waves' 0.20 -> 0.29 %, with nothing said.

    ``averaged_counts``: the reference is the float average of integer camera frames (Ctrl+R,
    ``--reference-frames``), judged as those frames' counts (its floor) at the top code of the bit
    depth that holds them: as a float its own maximum was its top, and an 8-bit reference whose
    bright squares peak at 229 read 25 % saturated (7 Dec 2026)."""
    a = np.asarray(reference)
    if averaged_counts and a.dtype.kind == "f":
        a = np.floor(np.clip(np.nan_to_num(a), 0, 65535)).astype(np.uint16)
    pct = saturation_pct(a)
    if pct <= SATURATION_MAX_PCT:
        return None
    return pct, (f"the reference has {pct:.1f} % of its pixels saturated: its bright squares are clipped, and every "
                 f"frame is measured against them (ray-traced, 42 % clipped: a bump's rms height error 0.05 -> "
                 f"0.18 %, waves 0.20 -> 0.29 %); lower the exposure or gain and take the reference again")


class LiveView:
    """Alignment and spectrum of validated frames over a chain
    (:class:`processing.chain_checkerboard.CheckerboardChain` or
    :class:`processing.chain_dots.DotsChain`); the carrier search is built on
    first use, and the spectrum of the last aligned frame is kept for
    :meth:`spectrum` of the same frame (the live worker's order)."""

    def __init__(self, chain, pattern):
        self.chain = chain
        self.pattern = pattern
        self._search = None
        self._shown = None

    def carrier_search(self):
        """:func:`processing.alignment.carrier_search` of the reference (built on first use)."""
        if self._search is None:
            from .alignment import carrier_search

            d = self.chain.demod
            self._search = carrier_search(self.chain.shape, d.freq, d.border_window)
        return self._search

    def alignment(self, frame) -> dict:
        """:meth:`processing.reconstruct.Reconstructor.alignment` of a validated frame."""
        chain = self.chain
        if self.pattern == "dots":
            from .piv import dot_alignment

            out = dot_alignment(frame, window_px=chain.piv.window_px)
            out["saturation_pct"] = saturation_pct(frame)
            out["reference"] = dot_alignment(chain.reference_image, window_px=chain.piv.window_px)
            return out
        from .alignment import checkerboard_alignment, frame_key

        g = chain.geometry
        out, shown = checkerboard_alignment(
            chain.demod, self.carrier_search(), chain.carriers, frame,
            theta_configured_deg=(float(g.theta_deg) if getattr(g, "setup", "tir") == "tir" else None),
            pattern_stretch_y=getattr(g, "pattern_stretch_y", None) or 1.0)
        out["saturation_pct"] = saturation_pct(frame)
        if "carrier_freq" in out:  # the board's period through the scale (Geometry.board_period_mm)
            out["board_period_mm"] = g.board_period_mm(out["carrier_freq"], frame.shape)
        # the display spectrum of the same FFT, for spectrum(frame) right after (the live worker's order)
        self._shown = (frame_key(frame), shown)
        return out

    def spectrum(self, frame, *, size: int = 256, max_freq: float = 0.25) -> dict:
        """:meth:`processing.reconstruct.Reconstructor.spectrum` of a validated frame."""
        if self.pattern == "dots":
            from .carriers import frame_spectrum

            return dict(frame_spectrum(frame, size=size, max_freq=max_freq), carriers=[])
        from .alignment import frame_key
        from .half_spectrum import display_spectrum_of

        d = self.chain.demod
        cached = self._shown
        if cached is not None and (size, max_freq) == (256, 0.25) and cached[0] == frame_key(frame):
            out = dict(cached[1])  # alignment(frame) just transformed this very frame
        else:
            search = self.carrier_search()
            spec = d.spectrum(frame)
            # the mean x border-window peak at DC removed, as for the carriers
            leak = None if search.window_spectrum is None else (d.last_mean, search.window_spectrum)
            out = display_spectrum_of(spec, self.chain.shape, leak=leak, size=size, max_freq=max_freq)
        carriers = [(float(f[1]), float(f[0])) for f in d.freq]
        out["carriers"] = carriers + [(-a, -b) for a, b in carriers]
        return out
