"""A small MEB master written from docs/protocols/meb.md alone (no code of the
twin's): frames `@ ID CMD ADDR CNT DATA FCS * LF`, FCS the XOR of every byte
from `@` to the last one before it. It talks to `twin serve` over TCP or a
serial device (a pseudo-terminal here), reads the inputs, writes VEL and the
digital outputs, watches RPM_M follow, and checks the error replies.

    python3 meb_master.py tcp HOST PORT
    python3 meb_master.py serial DEVICE

Prints one JSON object with what it saw; exits 1 with a message if the slave
breaks the spec.
"""
import json
import os
import select
import socket
import sys
import termios
import time
import tty

SLAVE = 1
TIMEOUT = 0.1  # the spec's default reply timeout


def fail(msg):
    print(msg, file=sys.stderr)
    sys.exit(1)


def fcs(data: bytes) -> int:
    x = 0
    for b in data:
        x ^= b
    return x


def frame(ident, cmd, addr, cnt, data=()):
    body = "@%02d%s%02X%02d" % (ident, cmd, addr, cnt) + "".join("%04X" % w for w in data)
    return (body + "%02X*\n" % fcs(body.encode())).encode()


class Link:
    def __init__(self, kind, *where):
        self.buf = b""
        if kind == "tcp":
            self.sock = socket.create_connection((where[0], int(where[1])), timeout=5)
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.fd = self.sock.fileno()
            self.send = self.sock.sendall
            self.recv = lambda: self.sock.recv(4096)
        else:
            self.fd = os.open(where[0], os.O_RDWR | os.O_NOCTTY)
            tty.setraw(self.fd)
            attrs = termios.tcgetattr(self.fd)
            attrs[4] = attrs[5] = termios.B115200
            termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
            self.send = lambda b: os.write(self.fd, b)
            self.recv = lambda: os.read(self.fd, 4096)

    def reply(self, timeout=TIMEOUT):
        """The next frame up to LF, or None after `timeout` of silence."""
        end = time.monotonic() + timeout
        while b"\n" not in self.buf:
            left = end - time.monotonic()
            if left <= 0 or not select.select([self.fd], [], [], left)[0]:
                return None
            chunk = self.recv()
            if not chunk:
                fail("the slave closed the link")
            self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\n")
        return line + b"\n"

    def transact(self, request, timeout=1.0):
        self.send(request)
        r = self.reply(timeout)
        if r is None:
            fail(f"no reply to {request!r}")
        return parse(r)


def parse(raw: bytes):
    """A reply frame: checks BOF, EOF, FCS and the id; returns its fields."""
    if not (raw.startswith(b"@") and raw.endswith(b"*\n")):
        fail(f"badly framed reply {raw!r}")
    body, check = raw[:-4], raw[-4:-2]
    if int(check, 16) != fcs(body):
        fail(f"bad FCS in reply {raw!r}")
    text = body.decode()
    ident, cmd, addr, cnt = int(text[1:3]), text[3:5], int(text[5:7], 16), int(text[7:9])
    data = [int(text[i:i + 4], 16) for i in range(9, len(text), 4)]
    if ident != SLAVE:
        fail(f"reply from slave {ident}: {raw!r}")
    return {"cmd": cmd, "addr": addr, "cnt": cnt, "data": data, "raw": raw.decode().strip()}


def read(link, cmd, addr, cnt):
    r = link.transact(frame(SLAVE, cmd, addr, cnt))
    if r["cmd"] != cmd or r["addr"] != addr or len(r["data"]) != cnt:
        fail(f"{cmd} {addr} {cnt}: unexpected reply {r['raw']}")
    return r["data"]


def write(link, cmd, addr, words):
    r = link.transact(frame(SLAVE, cmd, addr, len(words), words))
    if r["cmd"] != cmd or r["addr"] != addr or r["cnt"] != len(words) or r["data"]:
        fail(f"{cmd} {addr}: not a header echo: {r['raw']}")


def main():
    link = Link(*sys.argv[1:])
    seen = {}
    seen["ea"] = read(link, "EA", 0, 6)
    seen["errs_before"] = read(link, "FA", 1, 1)[0]

    # Error replies: address range (02) and unknown command (01).
    r = link.transact(frame(SLAVE, "EA", 0, 99))
    seen["er_range"] = r["data"] if r["cmd"] == "ER" else r["raw"]
    r = link.transact(frame(SLAVE, "QQ", 0, 1))
    seen["er_command"] = r["data"] if r["cmd"] == "ER" else r["raw"]

    # A bad FCS is ignored (no reply); garbage before `@` is dropped and the
    # frame after it answered once.
    bad = bytearray(frame(SLAVE, "EA", 0, 1))
    bad[-4:-2] = b"00" if bad[-4:-2] != b"00" else b"11"
    link.send(bytes(bad))
    seen["bad_fcs_reply"] = link.reply(0.3)
    link.send(b"zz\x00garbage" + frame(SLAVE, "EA", 3, 1))
    first = link.reply(1.0)
    seen["after_garbage"] = parse(first)["cmd"] if first else None
    seen["extra_reply"] = link.reply(0.3)
    seen["errs_after"] = read(link, "FA", 1, 1)[0]

    # Several requests without waiting: one reply each, in order.
    link.send(frame(SLAVE, "EA", 0, 1) + frame(SLAVE, "FA", 0, 1) + frame(SLAVE, "ED", 0, 1))
    seen["pipelined"] = [parse(link.reply(1.0) or fail("missing pipelined reply"))["cmd"] for _ in range(3)]

    # Drive: VEL 40 %, then outputs EN=0 (enabled), BRK=1 (released),
    # PRO=1 (boost off), DES=1 (no discharge), FR=0 (clockwise).
    write(link, "SA", 0, [1638])
    write(link, "SD", 0, [0x000E])

    def rpm():
        return read(link, "EA", 3, 1)[0]

    def settle(deadline_s):
        # Settled: two readings a second apart within 2 % of each other.
        end = time.monotonic() + deadline_s
        last = rpm()
        while time.monotonic() < end:
            time.sleep(1.0)
            now = rpm()
            if now > 200 and abs(now - last) <= 0.02 * now:
                return now
            last = now
        return last

    def rise_past(target, deadline_s):
        # Following: the first reading past `target`.
        end = time.monotonic() + deadline_s
        now = rpm()
        while now <= target and time.monotonic() < end:
            time.sleep(0.2)
            now = rpm()
        return now

    seen["rpm_low"] = settle(20)
    write(link, "SA", 0, [3276])
    seen["rpm_high"] = rise_past(1.4 * seen["rpm_low"], 20)
    seen["status"] = read(link, "FD", 0, 1)[0]
    print(json.dumps(seen))


main()
