"""The live window's logic without Qt: typed state and pure functions of frames, results and a clock.

The window (app/gui/window.py) builds widgets, forwards events here and draws what comes back:

* :mod:`.staleness` -- what each view shows, how old it is, and the age of every number
  derived from the processed maps (status bar "vs truth", probes, readouts); the reconstructor
  rebuild policy and which reference measured which frame (``ReferenceEpochs``);
* :mod:`.schedule` -- what each display tick draws (raw <= 60 Hz, maps <= 30 Hz in two halves:
  ``DrawClock.plan``), the replay queue (newest wanted frame only) and rates (shown, live);
* :mod:`.replay` -- the recording's reference and geometry before the window's, the frame label;
* :mod:`.region` -- the reference region kept on the frame;
* :mod:`.reference` -- a reference averaged only from frames that agree (still water);
* :mod:`.recording` -- the auto-trigger threshold in physical units and what the panel says;
* :mod:`.colour_range` -- which levels a map is drawn with (percentiles, a feature's core held)
  and when its colour range moves;
* :mod:`.memory` -- what a session remembers (``settings.json``), what it restores for which
  camera, and what came back.

None of these modules imports Qt or pyqtgraph (tests/app/test_gui_model.py checks it).
"""
