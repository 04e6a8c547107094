"""Messages for a camera that another program controls (app/gui/camera_messages.py)."""

from app.gui.camera_messages import explain_open_error, is_controlled_elsewhere
from drivers.base import CameraError


def test_aravis_privilege_error_is_explained():
    exc = CameraError("aravis:127.0.0.1: starting acquisition failed: Controller privilege required for "
                      "streaming control")
    msg = explain_open_error("aravis:127.0.0.1", exc)
    assert msg.startswith("camera aravis:127.0.0.1 is controlled by another program: close that program")
    assert msg.endswith("[camera said: " + str(exc) + "]")


def test_holder_host_is_named_when_the_protocol_tells():
    class CameraBusy(CameraError):
        pass

    exc = CameraBusy("aravis:10.0.0.7 is controlled by another program (held by 10.0.0.42:50123); close that "
                     "program and try again")
    msg = explain_open_error("aravis:10.0.0.7", exc)
    assert "controlled by another program on host 10.0.0.42:50123:" in msg
    exc2 = CameraError("busy")
    exc2.controller_host = "192.168.1.5"
    assert "on host 192.168.1.5" in explain_open_error("aravis:x", exc2)


def test_other_errors_keep_the_drivers_words():
    exc = CameraError("aravis:127.0.0.1 stopped answering (heartbeat failed); check power, cable and network")
    assert not is_controlled_elsewhere(exc)
    assert explain_open_error("aravis:127.0.0.1", exc) == str(exc)
