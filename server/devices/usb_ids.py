"""The USB vendor and product ids of the hardware burrforce drives itself, in one table that
imports nothing: the back-ends open their devices by them (``falcon.protocol``,
``actuators.board_protocol``) and the udev rules grant access to them (``udev``), so neither
side has to import the other."""

from __future__ import annotations

#: Novint Falcon: FTDI's vendor id with Novint's product id (libnifalcon).
FALCON_VID = 0x0403
FALCON_PID = 0xCB48
#: The burrforce vibration board: the pid.codes (0x1209) *test* PID, fine for development
#: boards and CI emulation only; a product built for others needs its own PID (pid.codes
#: grants them for open hardware).
BOARD_VID = 0x1209
BOARD_PID = 0x0001
