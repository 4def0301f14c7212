"""A master that behaves like the Controller_network project's Raspberry Pi
(docs/protocols/modbus8.md, "The real master's behaviour"): for every transaction it
opens the port, writes 8 bytes, waits a fixed time, reads once and closes the
port again. Its read has no timeout, so no reply hangs the real program and a
reply that is not whole in that one read misaligns it: this one records both instead (a hang is no reply
within 2 s), and which replies came after the fixed wait (`late`).

    python3 controller_network_master.py DEVICE CYCLES WAIT_MS [BUG]

BUG plants a mistake a student might make, for `twin check master` to find:
crc-low-first (the CRC sent low byte first, as standard Modbus RTU does) or
wrong-function (registers read with function 04, which the nodes lack).

Its loop: read the motor's state until operational (write 01 from 80, 81 from
02), then read rpm, every 20th cycle toggle the set point between 5000 and
10000, read the light sensor. Prints one JSON object with every transaction.
"""
import json
import os
import select
import sys
import termios
import time
import tty


HANG_S = 2.0


def crc16(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


BUG = sys.argv[4] if len(sys.argv) > 4 else None


def frame(ident, fc, addr, value):
    body = bytes([ident, fc, addr >> 8, addr & 0xFF, value >> 8, value & 0xFF])
    crc = crc16(body)
    if BUG == "crc-low-first":
        return body + bytes([crc & 0xFF, crc >> 8])
    return body + bytes([crc >> 8, crc & 0xFF])  # high byte first, as the Controller_network master


def transaction(path, request, wait_s):
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        tty.setraw(fd)
        attrs = termios.tcgetattr(fd)
        attrs[4] = attrs[5] = termios.B115200
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
        os.write(fd, request)
        time.sleep(wait_s)
        # The one read. The real one blocks until bytes come (no timeout);
        # here a reply that has not come in 2 s counts as a hang.
        late = not select.select([fd], [], [], 0)[0]
        if not select.select([fd], [], [], HANG_S)[0]:
            return b"", late
        reply = os.read(fd, 64)
    finally:
        os.close(fd)
    return reply, late


def check(request, reply):
    """None if `reply` is the whole, valid answer to `request`, else why not."""
    if len(reply) != 8:
        return f"{len(reply)} bytes in the one read"
    crc = crc16(reply[:6])
    if reply[6:] != bytes([crc >> 8, crc & 0xFF]):
        return "bad CRC"
    if reply[0] != request[0] or reply[2:4] != request[2:4]:
        return "reply to another request"
    if reply[1] & 0x80:
        return f"exception {reply[5]}"
    if request[1] == 6 and reply != request:
        return "write not echoed"
    return None


def main():
    path, cycles, wait_s = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]) / 1000
    log = []

    def ask(ident, fc, addr, value):
        if BUG == "wrong-function" and fc == 3:
            fc = 4
        req = frame(ident, fc, addr, value)
        rep, late = transaction(path, req, wait_s)
        problem = check(req, rep) if rep else "no reply: the real master would hang"
        log.append({"request": req.hex(), "reply": rep.hex(), "problem": problem, "late": late})
        return None if problem else int.from_bytes(rep[4:6], "big", signed=True)

    states = []
    for _ in range(20):
        state = ask(1, 3, 0x0001, 0)
        states.append(state)
        if state == 0x01:
            break
        if state == 0x80:
            ask(1, 6, 0x0001, 0x01)
        elif state == 0x02:
            ask(1, 6, 0x0001, 0x81)
    set_point = 10000
    rpms, lights = [], []
    for cycle in range(cycles):
        rpms.append(ask(1, 3, 0x0005, 1))
        if cycle % 20 == 19:
            set_point = 5000 if set_point == 10000 else 10000
            ask(1, 6, 0x0009, set_point)
        lights.append(ask(2, 3, 0x0006, 0))
        time.sleep(0.05)
    print(json.dumps({"states": states, "rpms": rpms, "lights": lights, "log": log}))


main()
