"""A student's Modbus RTU master, written with raw pyserial (no Modbus
library, nothing of the twin's): it polls the EV module's controllers for
their input registers and speed set point (docs/protocols/modbus-map.md),
one request at a time, and counts what went wrong instead of stopping.

    python3 modbus_student_master.py DEVICE --id 1,2 [--timeout-ms 1000]
        [--seconds 120] [--bug crc-swapped|never-times-out|floods]

Correct, it waits for each reply up to its timeout; a reply that is not
whole, not from the slave asked, or whose CRC does not hold is a frame
error: it lets the line go quiet, drops what came, and goes on to its next
request (no retry). The planted bugs:

- crc-swapped: its requests carry their CRC high byte first;
- never-times-out: it waits for a reply for ever;
- floods: it sends a cycle's four requests back to back, reply or not, and
  the next cycle 5 ms later (back to back, so that however fast a slave
  answers, a request always comes before the last one's reply).
"""
import argparse
import time

import serial

QUIET_S = 0.05
PAUSE_S = 0.02


def crc16(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def frame(body: bytes, swapped: bool) -> bytes:
    crc = crc16(body)
    lo, hi = crc & 0xFF, crc >> 8
    return body + (bytes([hi, lo]) if swapped else bytes([lo, hi]))


def reply_len(head: bytes):
    """The reply's whole length from its first three bytes, or None."""
    fc = head[1]
    if fc & 0x80:
        return 5
    if fc in (1, 2, 3, 4):
        return 5 + head[2]
    if fc in (5, 6, 15, 16):
        return 8
    return None


def read_reply(port, deadline):
    """Bytes of one reply, or what came before the deadline (None: never)."""
    got = b""
    need = 3
    while len(got) < need:
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0:
                return got
            port.timeout = left
        else:
            port.timeout = None
        chunk = port.read(need - len(got))
        got += chunk
        if len(got) >= 3 and need == 3:
            whole = reply_len(got)
            if whole is None:
                return got
            need = whole
    return got


def settle(port):
    """Lets the line go quiet, and drops what came."""
    port.timeout = QUIET_S
    while port.read(256):
        pass


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("device")
    parser.add_argument("--id", default="1")
    parser.add_argument("--timeout-ms", type=int, default=1000)
    parser.add_argument("--seconds", type=float, default=120)
    parser.add_argument("--bug", choices=["crc-swapped", "never-times-out", "floods"])
    args = parser.parse_args()
    ids = [int(i) for i in args.id.split(",")]
    port = serial.Serial(args.device, 115200, timeout=0.1)
    port.reset_input_buffer()
    requests = [
        bytes([4, 0, 0, 0, 10]),  # FC04: the ten input registers
        bytes([3, 0, 0, 0, 1]),  # FC03: VEL
    ]
    end = time.monotonic() + args.seconds
    errors = {"timeouts": 0, "frame errors": 0, "exceptions": 0}
    n = 0
    while time.monotonic() < end:
        for ident in ids:
            for pdu in requests:
                request = frame(bytes([ident]) + pdu, args.bug == "crc-swapped")
                port.write(request)
                n += 1
                if args.bug == "floods":
                    continue
                deadline = None
                if args.bug != "never-times-out":
                    deadline = time.monotonic() + args.timeout_ms / 1000
                got = read_reply(port, deadline)
                if not got:
                    errors["timeouts"] += 1
                elif (
                    len(got) < 5
                    or got[0] != ident
                    or (got[1] & 0x7F) != pdu[0]
                    or frame(got[:-2], False) != got
                ):
                    errors["frame errors"] += 1
                    settle(port)
                elif got[1] & 0x80:
                    errors["exceptions"] += 1
                time.sleep(PAUSE_S)
        if args.bug == "floods":
            time.sleep(0.005)
            port.reset_input_buffer()
    print(n, "requests;", errors)


main()
