"""The signals that stop the app the way Ctrl-C does, one list for every command and the window.

``tirdeflect process`` and ``tirdeflect record`` end on them as on Ctrl-C (the file closed valid, the
frames written kept) and the live window closes as its close button does; each exits 128 + the
signal's number, as a shell reports it (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP).
"""

from __future__ import annotations

import signal

__all__ = ["STOP_SIGNALS"]

#: besides Ctrl-C (SIGINT): what `timeout`, systemd and `kill` send (SIGTERM) and a terminal that closes
#: (SIGHUP; Windows has none)
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))
