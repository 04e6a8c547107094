"""Any vendor's GenTL producer (``.cti``) through harvesters.

Camera ids: ``gentl:<path to .cti>:<device>`` where ``<device>`` is a serial
number, a GenTL device id or an index into the producer's device list, e.g.
``gentl:/opt/vendor/lib/producer.cti:21234567``; ``gentl:<path.cti>`` opens the
first device, ``gentl:<device>`` searches every producer on
``GENICAM_GENTL64_PATH``.

Each fetched image is copied out of the GenTL buffer inside ``with buffer:``,
so the buffer goes back to the producer at once and the
:class:`~drivers.base.Frame` stays valid.

Honest limits, inherited from harvesters 1.4: it discards incomplete buffers
inside ``fetch`` (it requeues them and logs a warning). This driver counts them
through harvesters' ``INCOMPLETE_BUFFER`` callback
(``statistics()["n_incomplete_discarded"]``) and the consumer sees their ids
missing (id gaps); their pixels cannot be delivered.
"""

from __future__ import annotations

import glob
import os
import threading
import time
from typing import Dict, List, Optional, Tuple

import numpy as np

from .base import (
    Camera,
    CameraError,
    CameraInfo,
    CameraLost,
    CameraSettings,
    FetchTimeout,
    Frame,
    SettingError,
)
from .genicam_util import PIXEL_BITS, Features, apply_settings, read_settings

__all__ = ["GenTLCamera", "list_devices", "producers_on_path", "parse_camera_id", "viky_cti"]

# harvesters' internal GenTL wait per poll, in milliseconds (its unit); fetch's
# own timeout (seconds) bounds the total, so a fetch overruns by at most this.
_INTERNAL_WAIT_MS = 5


def producers_on_path() -> List[str]:
    """Every ``*.cti`` file in the directories of ``GENICAM_GENTL64_PATH`` (sorted, unique).

    The variable lists directories (or ``.cti`` files) separated by :data:`os.pathsep`
    (``:`` on Linux and macOS, ``;`` on Windows); the vendors' SDKs (pylon, Spinnaker,
    Vimba, ...) set it when they are installed.
    """
    found = []
    for d in os.environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep):
        if d and os.path.isdir(d):
            found += sorted(glob.glob(os.path.join(d, "*.cti")))
        elif d.endswith(".cti") and os.path.isfile(d):
            found.append(d)
    out = []
    for p in found:
        p = os.path.realpath(p)
        if p not in out:
            out.append(p)
    return out


def viky_cti() -> Optional[str]:
    """Path of ``viky.cti``, the GenTL producer shipped in the ``genicam`` wheel (None if absent)."""
    try:
        import genicam
    except ImportError:
        return None
    path = os.path.join(os.path.dirname(genicam.__file__), "viky.cti")
    return path if os.path.isfile(path) else None


def parse_camera_id(spec: str) -> Tuple[Optional[str], Optional[str]]:
    """Split the part after ``gentl:`` into ``(cti_path or None, device or None)``.

    ``/x/p.cti:123`` -> (``/x/p.cti``, ``123``); ``/x/p.cti`` -> (``/x/p.cti``, None);
    ``123`` -> (None, ``123``).
    """
    if not spec:
        return None, None
    idx = spec.lower().rfind(".cti")
    if idx < 0:
        return None, spec
    path, rest = spec[: idx + 4], spec[idx + 4 :]
    if rest and not rest.startswith(":"):
        raise CameraError(f"cannot parse GenTL camera id 'gentl:{spec}'; use 'gentl:/path/x.cti:DEVICE'")
    return path, (rest[1:] or None)


# -- one Harvester per producer, shared by the cameras of this process ---------------
_harvesters: Dict[str, list] = {}  # cti path -> [Harvester, refcount]
_h_lock = threading.Lock()


def _acquire_harvester(cti: str):
    try:
        from harvesters.core import Harvester
    except ImportError as exc:
        raise CameraError(f"harvesters is not installed ({exc}); pip install harvesters") from exc
    cti = os.path.realpath(cti)
    if not os.path.isfile(cti):
        raise CameraError(f"GenTL producer {cti!r} does not exist; give the path of the vendor's .cti file")
    with _h_lock:
        entry = _harvesters.get(cti)
        if entry is None:
            h = Harvester()
            h.add_file(cti, check_existence=True)
            h.update()
            entry = _harvesters[cti] = [h, 0]
        entry[1] += 1
        return entry[0]


def _release_harvester(cti: str) -> None:
    cti = os.path.realpath(cti)
    with _h_lock:
        entry = _harvesters.get(cti)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] <= 0:
            del _harvesters[cti]
            try:
                entry[0].reset()
            except Exception:
                pass


def _info_of(cti: str, index: int, d) -> CameraInfo:
    serial = str(getattr(d, "serial_number", "") or "")
    dev_id = str(getattr(d, "id_", "") or "")
    return CameraInfo(
        camera_id=f"gentl:{cti}:{serial or dev_id or index}",
        backend="gentl",
        vendor=str(getattr(d, "vendor", "") or ""),
        model=str(getattr(d, "model", "") or ""),
        serial=serial,
        address=dev_id,
    )


def list_devices(*, timeout_s: float = 3.0, producers: Optional[List[str]] = None) -> List[CameraInfo]:
    """Devices of every producer on ``GENICAM_GENTL64_PATH`` (or of ``producers``).

    Each producer is queried in a daemon thread bounded by ``timeout_s``
    seconds; a producer that fails or hangs is skipped.
    """
    result: List[CameraInfo] = []
    for cti in producers if producers is not None else producers_on_path():
        found: List[CameraInfo] = []

        def discover(cti=cti, found=found):
            with _h_lock:
                in_use = os.path.realpath(cti) in _harvesters
            h = _acquire_harvester(cti)
            try:
                if not in_use:
                    # harvesters' update() invalidates open acquirers of this producer: a
                    # producer with an open camera reports the list it had when opened
                    h.update()
                for i, d in enumerate(h.device_info_list):
                    found.append(_info_of(os.path.realpath(cti), i, d))
            finally:
                _release_harvester(cti)

        t = threading.Thread(target=discover, name="gentl-discovery", daemon=True)
        t.start()
        t.join(timeout_s)
        if not t.is_alive():
            result += found
    return result


class _GenApiFeatures(Features):
    """Node-map access through genicam.genapi (see :class:`drivers.genicam_util.Features`)."""

    def __init__(self, node_map):
        from genicam import genapi

        self.nm = node_map
        self.g = genapi

    def _node(self, name):
        try:
            return self.nm.get_node(name)
        except Exception:
            return None

    def kind(self, name):
        n = self._node(name)
        g = self.g
        if n is None or not g.is_available(n):
            return None
        return self.kind_of(n, (g.IEnumeration, g.ICommand, g.IBoolean, g.IFloat, g.IInteger, g.IString))

    def get(self, name):
        return self._node(name).value

    def set(self, name, value):
        n = self._node(name)
        k = self.kind(name)
        if k == "int":
            n.value = int(value)
        elif k == "float":
            n.value = float(value)
        elif k == "bool":
            n.value = bool(value)
        else:
            n.value = str(value)

    def int_bounds(self, name):
        n = self._node(name)
        return int(n.min), int(n.max), int(n.inc or 1)

    def float_bounds(self, name):
        n = self._node(name)
        return float(n.min), float(n.max)

    def enum_values(self, name):
        n = self._node(name)
        return [e.symbolic for e in n.entries if self.g.is_available(e)]

    def writable(self, name):
        n = self._node(name)
        return n is not None and self.g.is_writable(n)

    def execute(self, name):
        self._node(name).execute()


class GenTLCamera(Camera):
    """A GenTL device through harvesters, behind the :class:`~drivers.base.Camera` protocol.

    Parameters
    ----------
    spec : str
        The id without ``gentl:`` (see the module docstring).
    n_buffers : int
        GenTL buffers announced to the producer.

    Publishes :attr:`camera_id`, :attr:`info`, :meth:`settings`, :meth:`statistics`.
    """

    def __init__(self, spec: str, *, n_buffers: int = 16):
        if n_buffers < 1:
            raise ValueError(f"n_buffers must be >= 1; got {n_buffers}")
        self.cti, self.device = parse_camera_id(spec)
        self.n_buffers = int(n_buffers)
        self.camera_id = f"gentl:{spec}"
        self.info: Optional[CameraInfo] = None
        self._h = None
        self._ia = None
        self._features: Optional[_GenApiFeatures] = None
        self._acquiring = False
        self._closed = False
        self._reset_counters()

    def _reset_counters(self):
        self._n_delivered = 0
        self._n_incomplete_discarded = 0
        self._n_id_gaps = 0
        self._last_id = None
        self._shape = None

    # -- lifecycle -----------------------------------------------------------
    def _candidates(self) -> List[str]:
        if self.cti:
            return [self.cti]
        found = producers_on_path()
        if not found:
            raise CameraError(
                f"{self.camera_id}: no .cti given and GENICAM_GENTL64_PATH lists none; "
                "use 'gentl:/path/x.cti:DEVICE' or set GENICAM_GENTL64_PATH"
            )
        return found

    def open(self) -> "GenTLCamera":
        if self._closed:
            raise CameraError(f"{self.camera_id} was closed; create a new GenTLCamera")
        if self._ia is not None:
            return self
        seen = []
        for cti in self._candidates():
            h = _acquire_harvester(cti)
            try:
                infos = list(h.device_info_list)
                index = self._match(infos)
                seen += [_info_of(os.path.realpath(cti), i, d).camera_id for i, d in enumerate(infos)]
                if index is None:
                    _release_harvester(cti)
                    continue
                ia = h.create(index)
            except CameraError:
                _release_harvester(cti)
                raise
            except Exception as exc:
                _release_harvester(cti)
                raise CameraError(f"{self.camera_id}: the producer {cti} could not open the device: {exc}") from exc
            self.cti = os.path.realpath(cti)
            self._h, self._ia = h, ia
            self.info = _info_of(self.cti, index, infos[index])
            break
        else:
            raise CameraError(f"no GenTL device matches {self.camera_id!r}; found {seen or 'none'}")
        ia.num_buffers = self.n_buffers
        ia.timeout_period_on_update_event_data_call = _INTERNAL_WAIT_MS
        ia.add_callback(ia.Events.INCOMPLETE_BUFFER, self._on_incomplete)
        self._features = _GenApiFeatures(ia.remote_device.node_map)
        return self

    def _match(self, infos) -> Optional[int]:
        if not infos:
            return None
        if self.device is None:
            return 0
        for i, d in enumerate(infos):
            if self.device in (str(getattr(d, "serial_number", "")), str(getattr(d, "id_", ""))):
                return i
        if self.device.isdigit() and int(self.device) < len(infos):
            return int(self.device)
        return None

    def close(self) -> None:
        """Stop, destroy the acquirer and release the producer (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.stop()
        finally:
            ia, self._ia = self._ia, None
            self._features = None
            if ia is not None:
                try:
                    ia.destroy()
                except Exception:
                    pass
            if self._h is not None:
                self._h = None
                _release_harvester(self.cti)

    def __del__(self):
        # backup for a camera dropped without close(): release the device (bounded; a dead
        # device's objects are finalized in a daemon thread)
        try:
            self.close()
        except Exception:
            pass

    def _require_open(self, what):
        if self._ia is None:
            raise CameraError(f"{what}: {self.camera_id} is not open; call open() or use 'with camera:'")

    def _on_incomplete(self, *args):
        self._n_incomplete_discarded += 1

    # -- settings --------------------------------------------------------------
    def settings(self) -> CameraSettings:
        self._require_open("settings")
        try:
            return read_settings(self._features)
        except Exception as exc:
            raise CameraError(f"{self.camera_id}: reading settings failed: {exc}") from exc

    def configure(self, **values) -> CameraSettings:
        """Write settings, read them back. Raises SettingError naming the feature and its range."""
        self._require_open("configure")
        apply_settings(self._features, values, acquiring=self._acquiring)
        return self.settings()

    # -- acquisition -----------------------------------------------------------
    def start(self) -> None:
        self._require_open("start")
        if self._acquiring:
            return
        s = self.settings()
        if s.pixel_format not in PIXEL_BITS:
            raise SettingError(
                f"pixel_format {s.pixel_format!r} cannot be streamed as a mono image; "
                f"configure(pixel_format=...) one of {[f for f in PIXEL_BITS]}"
            )
        self._reset_counters()
        try:
            self._ia.start()
        except Exception as exc:
            raise CameraError(f"{self.camera_id}: starting acquisition failed: {exc}") from exc
        self._acquiring = True

    def stop(self) -> None:
        if not self._acquiring:
            return
        self._acquiring = False
        try:
            self._ia.stop()
        except Exception:
            pass

    def trigger_software(self) -> None:
        self._require_open("trigger_software")
        if self._features.kind("TriggerSoftware") != "command":
            raise CameraError(f"{self.camera_id} has no TriggerSoftware command; use trigger_mode='Off' or a line trigger")
        self._features.execute("TriggerSoftware")

    def fetch(self, timeout_s: float) -> Frame:
        """Wait at most ``timeout_s`` s (+ about 5 ms) for the next complete buffer; copy it out.

        Raises :class:`FetchTimeout` when none came, :class:`CameraLost` on a
        producer error, :class:`CameraError` when stopped/closed meanwhile.
        """
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0 seconds; got {timeout_s!r}")
        self._require_open("fetch")
        if not self._acquiring:
            raise CameraError(f"fetch: {self.camera_id} is not acquiring; call start() first")
        from genicam.gentl import TimeoutException

        deadline = time.monotonic() + timeout_s
        try:
            while True:  # 0.1 s slices, so stop()/close() from another thread ends the wait
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise FetchTimeout(
                        f"no frame from {self.camera_id} within {timeout_s:g} s (waiting for a trigger?)"
                    )
                try:
                    buf = self._ia.fetch(timeout=min(remaining, 0.1))
                    break
                except TimeoutException:
                    if not self._acquiring:
                        raise CameraError(f"fetch: {self.camera_id} was stopped or closed while waiting") from None
        except CameraError:
            raise
        except Exception as exc:
            if not self._acquiring:
                raise CameraError(f"fetch: {self.camera_id} was stopped or closed while waiting") from exc
            raise CameraLost(f"{self.camera_id}: the GenTL producer failed while fetching ({exc}); check the camera and reopen it") from exc
        host_ns = time.monotonic_ns()
        with buf:
            comp = buf.payload.components[0]
            fmt = str(comp.data_format)
            bits = PIXEL_BITS.get(fmt, 8)
            dtype = np.uint8 if bits == 8 else np.uint16
            h, w = int(comp.height), int(comp.width)
            image = np.array(comp.data.view(dtype)[: h * w].reshape(h, w), copy=True)
            frame_id = int(buf.frame_id)
            try:
                ts = int(buf.timestamp_ns) or None
            except Exception:  # producers without timestamps raise NotAvailable
                ts = None
        if self._last_id is not None and frame_id > self._last_id + 1:
            self._n_id_gaps += frame_id - self._last_id - 1
        self._last_id = frame_id
        self._n_delivered += 1
        return Frame(image=image, frame_id=frame_id, timestamp_ns=ts, host_timestamp_ns=host_ns, incomplete=False, bit_depth=bits)

    def statistics(self) -> dict:
        """``n_delivered``, ``n_incomplete_delivered`` (always 0: harvesters drops them),
        ``n_incomplete_discarded`` (dropped by harvesters), ``n_id_gap_frames``,
        and harvesters' ``num_images`` / ``fps``."""
        out = {
            "n_delivered": self._n_delivered,
            "n_incomplete_delivered": 0,
            "n_incomplete_discarded": self._n_incomplete_discarded,
            "n_id_gap_frames": self._n_id_gaps,
        }
        if self._ia is not None:
            try:
                out["num_images"] = int(self._ia.statistics.num_images)
                out["fps"] = float(self._ia.statistics.fps)
            except Exception:
                pass
        return out
