"""A student's MEB master (a supervisor), written from docs/protocols/meb.md
alone (no code of the twin's), for `twin check master` to grade. Every
cycle it reads the analog inputs of each slave (EA 00-05) and writes VEL
(SA 00) from the speed it read; it waits for each reply up to its timeout,
ignores replies that fail their FCS or come from another slave, takes an
error reply as the answer, retries once after a timeout, then goes on.

    python3 meb_student_master.py serial DEVICE [--id 1,2] [--bug BUG]...
    python3 meb_student_master.py tcp HOST PORT [--id 1,2] [--bug BUG]...

Bugs a student might make, planted on request:
  never-times-out   waits for a reply forever
  floods            sends request after request, never waiting for replies
  bad-fcs           its requests' FCS is off by one
  acts-on-bad-fcs   takes a reply whose FCS is wrong as good

Runs until killed, or --seconds.
"""
import argparse
import os
import select
import socket
import termios
import time
import tty

PERIOD = 0.02  # from one poll cycle to the next


def fcs(data: bytes) -> int:
    x = 0
    for b in data:
        x ^= b
    return x


class Master:
    def __init__(self, args):
        self.bugs = set(args.bug)
        self.timeout = args.timeout_ms / 1000.0
        self.buf = b""
        if args.kind == "tcp":
            self.sock = socket.create_connection((args.where[0], int(args.where[1])), timeout=10)
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.fd = self.sock.fileno()
            self._send = self.sock.sendall
            self._recv = lambda: self.sock.recv(4096)
        else:
            self.fd = os.open(args.where[0], os.O_RDWR | os.O_NOCTTY)
            tty.setraw(self.fd)
            attrs = termios.tcgetattr(self.fd)
            attrs[4] = attrs[5] = termios.B115200
            termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
            self._send = lambda b: os.write(self.fd, b)
            self._recv = lambda: os.read(self.fd, 4096)

    def frame(self, ident, cmd, addr, cnt, data=()):
        body = "@%02d%s%02X%02d" % (ident, cmd, addr, cnt) + "".join("%04X" % w for w in data)
        check = fcs(body.encode())
        if "bad-fcs" in self.bugs:
            check ^= 1
        return (body + "%02X*\n" % check).encode()

    def drain(self):
        while select.select([self.fd], [], [], 0)[0]:
            if not self._recv():
                raise SystemExit("the slaves hung up")

    def next_line(self, deadline):
        """The next line up to LF, from its last @; None at the deadline."""
        while b"\n" not in self.buf:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None
            if not select.select([self.fd], [], [], left)[0]:
                return None
            chunk = self._recv()
            if not chunk:
                raise SystemExit("the slaves hung up")
            self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\n")
        at = line.rfind(b"@")
        return line[at:] + b"\n" if at >= 0 else b""

    def good(self, reply, ident, cmd, addr):
        """The reply's words if it answers the request, else None."""
        text = reply.decode("ascii", "replace")
        if len(text) < 13 or not text.endswith("*\n"):
            return None
        body, check = text[:-4], text[-4:-2]
        if "acts-on-bad-fcs" not in self.bugs:
            try:
                if int(check, 16) != fcs(body.encode()):
                    return None
            except ValueError:
                return None
        if body[1:3] != "%02d" % ident:
            return None
        if body[3:5] == "ER":
            return "error"
        if body[3:5] != cmd or body[5:7] != "%02X" % addr:
            return None
        data = body[9:]
        return [int(data[i:i + 4], 16) for i in range(0, len(data), 4)]

    def transact(self, ident, cmd, addr, cnt, data=()):
        request = self.frame(ident, cmd, addr, cnt, data)
        if "floods" in self.bugs:
            self._send(request)
            self.drain()
            return None
        for _attempt in range(2):
            self._send(request)
            deadline = None if "never-times-out" in self.bugs else time.monotonic() + self.timeout
            while True:
                line = self.next_line(deadline)
                if line is None:
                    break
                answer = self.good(line, ident, cmd, addr)
                if answer is not None:
                    return answer
        return None

    def cycle(self, ids):
        for ident in ids:
            inputs = self.transact(ident, "EA", 0, 6)
            if isinstance(inputs, list) and len(inputs) == 6:
                vel = min(inputs[3] // 2, 4095)
                self.transact(ident, "SA", 0, 1, [vel])
            elif "floods" in self.bugs:
                self.transact(ident, "SA", 0, 1, [0])


def main():
    p = argparse.ArgumentParser()
    p.add_argument("kind", choices=["serial", "tcp"])
    p.add_argument("where", nargs="+")
    p.add_argument("--id", default="1")
    p.add_argument("--bug", action="append", default=[],
                   choices=["never-times-out", "floods", "bad-fcs", "acts-on-bad-fcs"])
    p.add_argument("--timeout-ms", type=float, default=100.0)
    p.add_argument("--seconds", type=float, default=None)
    args = p.parse_args()
    ids = [int(i) for i in args.id.split(",")]
    master = Master(args)
    end = None if args.seconds is None else time.monotonic() + args.seconds
    while end is None or time.monotonic() < end:
        started = time.monotonic()
        master.cycle(ids)
        if "floods" not in master.bugs:
            time.sleep(max(0.0, PERIOD - (time.monotonic() - started)))


if __name__ == "__main__":
    main()
