"""Aravis's device list read while a camera goes away (no camera needed).

Seen once in the suite (7 Dec 2026, test_aravis.py's dead-camera test beside a restarted fake camera):
``Aravis.get_device_id(i)`` raised UnicodeDecodeError on a half-written entry, the discovery thread died
with it and the search listed nothing. Such an entry is skipped now and the others are listed. The list
is Aravis's own functions (``get_n_devices``, ``get_device_*``), given here by a stand-in whose second
entry cannot be read, because the race cannot be made on demand with the real fake camera.
"""

from __future__ import annotations

import drivers.aravis as aravis


class _ListBeingRewritten:
    """Aravis's device-list functions over three entries, the second half-written."""

    ids = ["Fake-1", None, "Basler-42"]

    def enable_interface(self, name):
        pass

    def update_device_list(self):
        pass

    def get_n_devices(self):
        return len(self.ids)

    def get_device_id(self, i):
        if self.ids[i] is None:
            raise UnicodeDecodeError("utf-8", b"Fa\x00\xff", 2, 3, "invalid continuation byte")
        return self.ids[i]

    def get_device_protocol(self, i):
        return "Fake" if self.ids[i].startswith("Fake") else "GigEVision"

    def get_device_vendor(self, i):
        return "vendor"

    def get_device_model(self, i):
        return "model"

    def get_device_serial_nbr(self, i):
        return str(i)

    def get_device_address(self, i):
        return "192.168.1.%d" % (10 + i)


def test_an_entry_that_cannot_be_read_is_skipped_and_the_others_listed(monkeypatch):
    monkeypatch.setattr(aravis, "_aravis", lambda: _ListBeingRewritten())
    found = aravis.list_devices(timeout_s=5.0, include_fake=True)
    assert [c.camera_id for c in found] == ["aravis:Fake-1", "aravis:Basler-42"]
    assert [c.camera_id for c in aravis.list_devices(timeout_s=5.0)] == ["aravis:Basler-42"]
