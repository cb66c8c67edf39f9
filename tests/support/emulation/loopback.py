"""A loopback USB device for testing the emulation itself (and as the smallest example of an
:class:`~.function.EmulatedFunction`).

pid.codes test identity 1209:0002. Interface 0, vendor class:

- bulk OUT 0x01: every packet written comes back, as one transfer, on bulk IN 0x81;
- interrupt IN 0x82 (1 ms): answers only what the control channel ``push``-es, so a host
  read on it stays pending until then (or until the host's timeout discards it);
- vendor request 0x01 (OUT) stores its data stage; 0x02 (IN) returns it; 0x03 STALLs.
"""

from __future__ import annotations

from collections import deque
from typing import Any

from .function import DIR_IN, TYPE_MASK, TYPE_VENDOR, EmulatedFunction, Endpoint, Stall

EP_OUT = 0x01
EP_IN = 0x81
EP_INT_IN = 0x82
REQ_STORE = 0x01
REQ_LOAD = 0x02
REQ_STALL = 0x03


class LoopbackFunction(EmulatedFunction):
    vendor_id = 0x1209
    product_id = 0x0002
    manufacturer = "burrforce"
    product = "usbfs loopback (emulated)"
    serial = "LOOP0001"
    endpoints = (Endpoint(EP_OUT), Endpoint(EP_IN),
                 Endpoint(EP_INT_IN, "interrupt", max_packet=64, interval=1))

    def __init__(self) -> None:
        self.echo: deque[bytes] = deque()
        self.pushed: deque[bytes] = deque()
        self.stored = b""
        self.received: list[str] = []

    def control(self, request_type: int, request: int, value: int, index: int,
                data_or_length: bytes | int) -> bytes | int | None:
        if request_type & TYPE_MASK == TYPE_VENDOR:
            if request == REQ_STORE and not request_type & DIR_IN:
                self.stored = bytes(data_or_length)
                return len(self.stored)
            if request == REQ_LOAD and request_type & DIR_IN:
                return self.stored
            return None
        return super().control(request_type, request, value, index, data_or_length)

    def out(self, endpoint: int, data: bytes) -> None:
        if endpoint != EP_OUT:
            raise Stall(f"no OUT endpoint {endpoint:#04x}")
        self.received.append(data.hex())
        self.echo.append(data)

    def in_(self, endpoint: int, max_len: int) -> bytes | None:
        queue = self.echo if endpoint == EP_IN else self.pushed
        if not queue:
            return None
        data = queue[0]
        if len(data) <= max_len:
            queue.popleft()
            return data
        queue[0] = data[max_len:]
        return data[:max_len]

    def _push(self, data_hex: str) -> int:
        self.pushed.append(bytes.fromhex(data_hex))
        self.wake()
        return len(self.pushed)

    def _state(self) -> dict[str, Any]:
        return {"received": list(self.received), "stored": self.stored.hex(),
                "echo_queued": len(self.echo), "pushed_queued": len(self.pushed)}

    def commands(self) -> dict[str, Any]:
        return {"push": self._push, "state": self._state}
