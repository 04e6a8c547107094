"""A lossy GigE Vision link whose camera honours packet-resend requests (fault injection for tests).

``arv-fake-gv-camera-0.8 -r N`` drops stream packets but never answers a
GVCP PACKETRESEND request, so it cannot show what resend recovers. A real
camera keeps recent packets and sends them again when asked. :class:`LossyLink`
sits between Aravis and a loss-free fake camera and plays both parts of such
a link:

* the network: it forwards GVCP (control) both ways, and GVSP (stream)
  packets from the camera to the host, dropping ``loss_per_thousand`` of the
  stream packets at random -- first sends and resends alike;
* the camera's resend buffer: it keeps the stream packets of the last
  ``keep_blocks`` frames and answers PACKETRESEND by sending the asked packets
  again.

Aravis talks to ``aravis:<link_ip>`` (default 127.0.0.2; every 127.x.y.z is
local on Linux). The link rewrites the stream destination Aravis writes into
the camera (GevSCPHostPort, GevSCDA) to itself, and the address in discovery
answers to its own. Nothing of tirdeflect or Aravis is replaced: the thing
under test (driver, Aravis' resend logic, recorder) runs as in the field.
"""

from __future__ import annotations

import collections
import random
import select
import socket
import struct
import threading

GVCP_PORT = 3956
_DISCOVERY_ACK = 0x0003
_PACKETRESEND_CMD = 0x0040
_WRITEREG_CMD = 0x0082
_SCP0_HOST_PORT = 0x0D00  # GevSCPHostPort (low 16 bits)
_SCDA0 = 0x0D18  # GevSCDA: stream destination IPv4 address
_DISCOVERY_IP_OFFSET = 8 + 0x24  # current IP address in a discovery answer (after the 8-byte GVCP header)


def _ip_int(address: str) -> int:
    return struct.unpack(">I", socket.inet_aton(address))[0]


class LossyLink:
    """GVCP/GVSP relay ``link_ip`` <-> ``camera_ip`` that loses stream packets and serves resend requests.

    Publishes ``forwarded``, ``dropped`` (first sends lost; per block: ``dropped_in_block``),
    ``resend_requests``, ``resent`` (packets sent again), ``resent_dropped`` (of those, lost again),
    ``resend_unknown`` (asked packets no longer kept).
    """

    def __init__(self, camera_ip: str = "127.0.0.1", link_ip: str = "127.0.0.2", *, loss_per_thousand: int = 20,
                 keep_blocks: int = 64, seed: int = 1):
        self.camera_ip = camera_ip
        self.link_ip = link_ip
        self.camera_id = f"aravis:{link_ip}"
        self.loss = loss_per_thousand / 1000.0
        self.keep_blocks = int(keep_blocks)
        self._rng = random.Random(seed)
        self._stop = threading.Event()
        self._thread = None
        self._clients = {}  # GVCP request id -> client address
        self._last_client = None
        self._stream_dest = None  # (ip, port) Aravis wants the stream at
        self._blocks = collections.OrderedDict()  # block id -> {packet id: bytes}
        self.forwarded = self.dropped = self.resend_requests = self.resent = self.resent_dropped = 0
        #: first sends lost, per GVSP block id (16 bit): a frame's own losses
        self.dropped_in_block = collections.Counter()
        self.resend_unknown = 0

    def start(self) -> "LossyLink":
        self.gvcp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.gvcp.bind((self.link_ip, GVCP_PORT))
        self.to_camera = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.to_camera.bind((self.link_ip, 0))
        self.gvsp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.gvsp.bind((self.link_ip, 0))
        self.gvsp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        self._thread = threading.Thread(target=self._run, name="lossy-link", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        for s in (self.gvcp, self.to_camera, self.gvsp):
            s.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # ------------------------------------------------------------------ relay
    def _run(self):
        socks = [self.gvcp, self.to_camera, self.gvsp]
        while not self._stop.is_set():
            ready, _, _ = select.select(socks, [], [], 0.1)
            for s in ready:
                try:
                    data, addr = s.recvfrom(65536)
                except OSError:
                    continue
                if s is self.gvcp:
                    self._from_host(data, addr)
                elif s is self.to_camera:
                    self._from_camera(data)
                else:
                    self._stream_packet(data)

    def _from_host(self, data: bytes, addr) -> None:
        if len(data) < 8:
            return
        command, length, req_id = struct.unpack(">HHH", data[2:8])
        if command == _PACKETRESEND_CMD:
            self._resend(data[8:8 + length], addr)
            return
        if command == _WRITEREG_CMD:
            data = self._rewrite_writereg(data, addr)
        self._clients[req_id] = addr
        self._last_client = addr
        self.to_camera.sendto(data, (self.camera_ip, GVCP_PORT))

    def _rewrite_writereg(self, data: bytes, addr) -> bytes:
        out = bytearray(data)
        for off in range(8, len(data) - 7, 8):
            reg, value = struct.unpack(">II", data[off:off + 8])
            if reg == _SCP0_HOST_PORT:
                port = value & 0xFFFF
                ip = self._stream_dest[0] if self._stream_dest else addr[0]
                self._stream_dest = (ip, port) if port else None
                if port:
                    out[off + 4:off + 8] = struct.pack(">I", (value & 0xFFFF0000) | self.gvsp.getsockname()[1])
            elif reg == _SCDA0:
                ip = socket.inet_ntoa(struct.pack(">I", value))
                self._stream_dest = (ip, self._stream_dest[1] if self._stream_dest else 0)
                out[off + 4:off + 8] = struct.pack(">I", _ip_int(self.link_ip))
        return bytes(out)

    def _from_camera(self, data: bytes) -> None:
        if len(data) < 8:
            return
        command, _, ack_id = struct.unpack(">HHH", data[2:8])
        if command == _DISCOVERY_ACK and len(data) >= _DISCOVERY_IP_OFFSET + 4:
            data = (data[:_DISCOVERY_IP_OFFSET] + struct.pack(">I", _ip_int(self.link_ip))
                    + data[_DISCOVERY_IP_OFFSET + 4:])
        client = self._clients.pop(ack_id, self._last_client)
        if client is not None:
            self.gvcp.sendto(data, client)

    def _stream_packet(self, data: bytes) -> None:
        if len(data) < 8 or self._stream_dest is None:
            return
        block_id = struct.unpack(">H", data[2:4])[0]
        packet_id = int.from_bytes(data[5:8], "big")
        packets = self._blocks.get(block_id)
        if packets is None:
            packets = self._blocks[block_id] = {}
            while len(self._blocks) > self.keep_blocks:
                self._blocks.popitem(last=False)
        packets[packet_id] = data
        if not self._send_lossy(data):
            self.dropped += 1
            self.dropped_in_block[block_id] += 1

    def _send_lossy(self, data: bytes) -> bool:
        if self._rng.random() < self.loss:
            return False
        self.gvsp.sendto(data, self._stream_dest)
        self.forwarded += 1
        return True

    def _resend(self, payload: bytes, addr) -> None:
        if len(payload) < 12 or self._stream_dest is None:
            return
        block_id, first, last = struct.unpack(">III", payload[:12])
        self.resend_requests += 1
        packets = self._blocks.get(block_id & 0xFFFF, {})
        for pid in range(first & 0xFFFFFF, (last & 0xFFFFFF) + 1):
            data = packets.get(pid)
            if data is None:
                self.resend_unknown += 1
                continue
            self.resent += 1
            if not self._send_lossy(data):
                self.resent_dropped += 1
