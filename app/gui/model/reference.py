"""What the window says about a reference capture and the pattern its reference shows.

The averaging of a capture's frames, and its refusal when they disagree (the water moves), is
:mod:`processing.reference_average`, which ``tirdeflect process --reference-frames`` shares; here
the label and banner the window shows after a refusal, and the maps' words when the reference does
not show the chosen pattern.
"""

from __future__ import annotations

from typing import Optional

__all__ = ["capture_failed_label", "capture_failed_message", "pattern_mismatch_messages"]


def capture_failed_label(error: str, previous_kept: bool) -> str:
    """The reference label (red) after a capture failed with ``error``: "REFUSED" when the water moved."""
    return (("REFUSED: the water is moving" if "the water is moving" in error else "capture failed")
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
