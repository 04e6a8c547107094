"""What the window says about a reference capture and the pattern its reference shows.

The averaging of a capture's frames, and its refusal when they disagree (the water moves), is
:mod:`processing.reference_average`, which ``tirdeflect process --reference-frames`` shares; here
the label and banner the window shows after a refusal, and the maps' words when the reference does
not show the chosen pattern.
"""

from __future__ import annotations

from typing import Optional

__all__ = ["capture_failed_label", "capture_failed_message", "pattern_mismatch_messages", "no_pattern_error",
           "NO_PATTERN", "incomplete_frame_messages", "maps_messages"]

#: what a refused capture of frames showing no checkerboard says first (and its label keys on)
NO_PATTERN = "the camera image shows no checkerboard"


def no_pattern_error(disagreement: str) -> str:
    """The refusal of a capture whose first frame shows no checkerboard (no carrier peak) and whose frames
    differ (``disagreement``: :meth:`~processing.reference_average.ReferenceReport.disagreement`). It said only
    "the water is moving: wait and capture again", on a camera that did not see the pattern at all (by-hand
    trial with the fake GigE camera, whose frames are moving stripes, 7 Dec 2026): waiting would never help."""
    return (f"{NO_PATTERN} (no carrier peak in its first frame): point the camera at the pattern under the "
            "water, check its focus and light (the Alignment tab shows what it sees), then capture again. "
            f"Its frames also differ from each other: {disagreement}.")


def capture_failed_label(error: str, previous_kept: bool) -> str:
    """The reference label (red) after a capture failed with ``error``: "REFUSED" when the water moved."""
    return (("REFUSED: no checkerboard in the image" if NO_PATTERN in error else
             "REFUSED: the water is moving" if "the water is moving" in error else "capture failed")
            + (" (previous reference kept)" if previous_kept else ""))


def capture_failed_message(error: str, previous_kept: bool) -> str:
    """The banner after a capture failed with ``error``: what stays in use. (The error itself used to end with
    "The previous reference is kept." also when there was none: by-hand trial 2 Dec 2026.)"""
    return (f"Reference capture failed: {error} "
            + ("The previous reference stays in use." if previous_kept else
               "There is no reference yet: no heights until one is captured on still water."))


def pattern_mismatch_messages(problem: Optional[str]) -> tuple:
    """What the maps say while the reference does not show the chosen pattern (``problem``, from
    :func:`app.gui.alignment.periodic_pattern`; None: it does): ``(full, short)`` -- the full text in red on the
    height map, a few words on the small maps, ``("", None)`` when there is nothing to say. Those heights are
    wrong (random dots chosen on a checkerboard: 136-432 % off the truth), and the banner saying so can be
    closed: the maps themselves keep saying it (by-hand trial 2 Dec 2026)."""
    if not problem:
        return "", None
    return (f"NOT the chosen pattern, these heights are wrong: {problem}",
            "NOT the chosen pattern (see Height)")


def incomplete_frame_messages(missing_pct: float) -> tuple:
    """What the maps say over the heights of an INCOMPLETE frame (``missing_pct``: % of its bytes the camera's
    link lost, stored as 0): ``(full, short)`` as :func:`pattern_mismatch_messages`, ``("", None)`` for a whole
    frame. The status bar counted such frames, but the maps of one, wrong along the lost rows (stripes of
    zeros in the raw frame, spread by the band-pass), were drawn as any others (by-hand trial with the fake
    GigE camera dropping packets, 7 Dec 2026)."""
    if not missing_pct > 0:
        return "", None
    return (f"INCOMPLETE frame: {missing_pct:.2g} % of its pixels were lost on the camera's link (stored as 0): "
            "these heights are wrong along those rows", "INCOMPLETE frame (see Height)")


def maps_messages(*messages: tuple) -> tuple:
    """The ``(full, short)`` pairs that have something to say, joined (the first's short words kept)."""
    said = [m for m in messages if m[0]]
    if not said:
        return "", None
    return "; ".join(m[0] for m in said), next((m[1] for m in said if m[1]), None)
