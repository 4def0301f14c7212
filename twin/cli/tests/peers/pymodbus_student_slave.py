"""A student's EV module controller written with pymodbus, a Modbus stack
the twin did not write: the register map of the Modbus map page
(docs/protocols/modbus-map.md), its range checks and its exceptions, served
over Modbus TCP or Modbus RTU on a serial port (a pseudo-terminal in the
tests). `twin check slave --suite modbus-tcp-slave|modbus-rtu-slave` checks
it; each --bug plants one mistake a student makes, for the suite to find.

    pymodbus_student_slave.py tcp PORT_FILE [--bug NAME]...
    pymodbus_student_slave.py rtu DEVICE [--bug NAME]...

TCP listens on a free port and writes it to PORT_FILE; RTU prints
"serving" once the port is open.

Bugs: answers-bad-crc (a frame with a wrong CRC is answered as if it were
right), crc-byte-order-swapped (replies carry their CRC high byte first),
wrong-exception-code (an illegal address is answered 03, not 02),
answers-broadcast (unit 0 is taken for the module's own id),
no-range-check (VEL and RPM_WIN take any value), wrong-transaction-id (TCP
replies carry transaction id 0).
"""
import argparse
import asyncio
import logging
import os
import struct
import sys
import time

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.exceptions import NoSuchIdException
from pymodbus.pdu import ExceptionResponse
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadDiscreteInputsRequest,
    WriteSingleCoilRequest,
)
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
)
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.transport.transport import ModbusProtocol

BUGS = (
    "answers-bad-crc",
    "crc-byte-order-swapped",
    "wrong-exception-code",
    "answers-broadcast",
    "no-range-check",
    "wrong-transaction-id",
)
UNIT = 1
# A pseudo-terminal carries no line timing: this much quiet ends a frame
# (the page's 3.5 characters, widened for a loaded machine).
SILENCE_S = 0.02


def crc16(data):
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


class Module(ModbusServerContext):
    """The module's four tables and their rules, in place of pymodbus'
    sequential blocks, which know no holes and no ranges."""

    # Function codes pymodbus passes in, by table.
    TABLES = {1: "co", 5: "co", 15: "co", 2: "di", 3: "hr", 6: "hr", 16: "hr", 4: "ir"}

    def __init__(self, tcp, bugs):
        # pymodbus calls a context of its "old simulator" kind for every
        # value; the module is one.
        self.old_simulator = True
        self.simdevices = []
        self.tcp = tcp
        self.bugs = bugs
        # V2, I, V1, RPM_M, RPM_L, LDR, HALL, SOC, ERRS, STATUS.
        self.ir = [1650, 12, 1933, 0, 0, 2400, 0, 1000, 0, 0]
        # VEL, LDR_TH, RPM_WIN.
        self.hr = [0, 1800, 100]
        # EN, BRK, PRO, DES, FR, CHG (1: inactive), two holes, LDR_ADAPT.
        self.co = [True] * 6 + [False, False, True]
        self.di = [False] * 12

    def device_ids(self):
        return [UNIT]

    def own(self, device_id):
        ids = {UNIT, 0, 255} if self.tcp else {UNIT}
        if "answers-broadcast" in self.bugs:
            ids.add(0)
        if device_id not in ids:
            raise NoSuchIdException(f"unit {device_id}")

    def illegal_address(self):
        if "wrong-exception-code" in self.bugs:
            return ExcCodes.ILLEGAL_VALUE
        return ExcCodes.ILLEGAL_ADDRESS

    async def async_getValues(self, device_id, func_code, address, count=1):
        self.own(device_id)
        if func_code not in self.TABLES:
            return ExcCodes.ILLEGAL_FUNCTION
        table = getattr(self, self.TABLES[func_code])
        if address + count > len(table):
            return self.illegal_address()
        return list(table[address : address + count])

    async def async_setValues(self, device_id, func_code, address, values):
        self.own(device_id)
        if func_code not in self.TABLES or self.TABLES[func_code] not in ("co", "hr"):
            return ExcCodes.ILLEGAL_FUNCTION
        name = self.TABLES[func_code]
        table = getattr(self, name)
        if address + len(values) > len(table):
            return self.illegal_address()
        spots = range(address, address + len(values))
        if name == "co" and any(i in (6, 7) for i in spots):
            return self.illegal_address()
        if name == "hr" and "no-range-check" not in self.bugs:
            limits = {0: range(0, 4096), 1: range(0, 4096), 2: range(1, 1001)}
            if any(v not in limits[i] for i, v in zip(spots, values)):
                return ExcCodes.ILLEGAL_VALUE
        table[address : address + len(values)] = values
        return None


def counted(request, most):
    """pymodbus refuses a read count outside the standard's limits while
    decoding, and answers it exception 01 with function 00; the standard
    (and the page) want exception 03 to the request's function. The
    student's request classes take the count and judge it when serving."""

    class Counted(request):
        def decode(self, data):
            self.address, self.count = struct.unpack(">HH", data[:4])

        async def datastore_update(self, context, device_id):
            if not 1 <= self.count <= most:
                return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
            return await super().datastore_update(context, device_id)

    return Counted


class CoilWrite(WriteSingleCoilRequest):
    """pymodbus takes any value but 0000 for a coil's ON; the standard
    allows FF00 and 0000 only, anything else exception 03."""

    def decode(self, data):
        self.address, self.value = struct.unpack(">HH", data[:4])
        self.bits = [self.value == 0xFF00]

    async def datastore_update(self, context, device_id):
        if self.value not in (0xFF00, 0x0000):
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        return await super().datastore_update(context, device_id)


STANDARD_PDUS = [
    counted(ReadCoilsRequest, 2000),
    counted(ReadDiscreteInputsRequest, 2000),
    counted(ReadHoldingRegistersRequest, 125),
    counted(ReadInputRegistersRequest, 125),
    CoilWrite,
]


def silence_ends_frames():
    """pymodbus' RTU framer reads no line timing ("timing cannot be
    guaranteed"), so bytes that are no frame stay in its buffer and spoil
    the next request. The page requires the silence to drop them: a
    student adds that rule to the port's reader."""
    received = ModbusProtocol.datagram_received

    def with_silence(self, data, addr):
        now = time.monotonic()
        if now - getattr(self, "last_byte_at", now) > SILENCE_S:
            self.recv_buffer = b""
        self.last_byte_at = now
        received(self, data, addr)

    ModbusProtocol.datagram_received = with_silence


def tracer(bugs):
    def packet(sending, data):
        if sending:
            if "crc-byte-order-swapped" in bugs and len(data) >= 4:
                return data[:-2] + data[-1:] + data[-2:-1]
            if "wrong-transaction-id" in bugs and len(data) >= 7:
                return b"\0\0" + data[2:]
            return data
        if "answers-bad-crc" in bugs and len(data) >= 4:
            # Any CRC is taken: the one the bytes give is put in its place.
            body = data[:-2]
            return body + crc16(body).to_bytes(2, "little")
        return data

    return packet


async def serve(args, bugs):
    tcp = args.framing == "tcp"
    context = Module(tcp, bugs)
    common = dict(
        ignore_missing_devices=True,
        trace_packet=tracer(bugs),
        custom_pdu=STANDARD_PDUS,
    )
    if tcp:
        server = ModbusTcpServer(
            context, framer=FramerType.SOCKET, address=("127.0.0.1", 0), **common
        )
        await server.serve_forever(background=True)
        port = server.transport.sockets[0].getsockname()[1]
        with open(args.target + ".tmp", "w") as f:
            f.write(str(port))
        os.replace(args.target + ".tmp", args.target)
    else:
        silence_ends_frames()
        server = ModbusSerialServer(
            context,
            framer=FramerType.RTU,
            port=args.target,
            baudrate=args.baud,
            broadcast_enable="answers-broadcast" not in bugs,
            **common,
        )
        await server.serve_forever(background=True)
        print("serving", flush=True)
    await server.serving


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("framing", choices=("tcp", "rtu"))
    parser.add_argument("target", help="TCP: the file the port is written to; RTU: the device")
    parser.add_argument("--baud", type=int, default=115200)
    parser.add_argument("--bug", action="append", default=[], choices=BUGS)
    args = parser.parse_args()
    logging.disable(logging.CRITICAL)
    asyncio.run(serve(args, set(args.bug)))


if __name__ == "__main__":
    sys.exit(main())
