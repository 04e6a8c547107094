"""What the camera panel's Apply writes: only the settings the open camera has.

The panel's editors hold a value for every setting of :class:`drivers.base.CameraSettings`; a camera without one
of them (the Aravis fake GigE camera and many real GigE cameras have ``GainRaw`` in device units only, no gain in
dB) reads it back as None and its editor is greyed out. Sending the greyed value anyway made the driver refuse
the whole write ("gain_db: this camera has no Gain feature"): exposure, frame rate, ROI and pixel format could
never be changed on such a camera (by-hand trial with the fake GigE camera, 7 Dec 2026).
"""

from __future__ import annotations

from typing import Optional

__all__ = ["settings_to_write"]


def settings_to_write(edited: dict, accepted: Optional[object]) -> dict:
    """The panel's ``edited`` values (names of ``CameraSettings``) less those the camera does not have.

    ``accepted``: the settings the camera last read back (None: not known yet, everything is sent). A name whose
    accepted value is None is a feature the camera lacks; names ``CameraSettings`` does not have are kept (the
    driver names them in its refusal).
    """
    if accepted is None:
        return dict(edited)
    return {k: v for k, v in edited.items() if not (hasattr(accepted, k) and getattr(accepted, k) is None)}
