"""A student's supervisor, as a student of the M3CVME lab would write one,
outside the twin's code: master of the module's bus (the serial line, via
pyserial) and a TCP server for remote clients, answered from the image of
the slave it polls, as the MEB page says (docs/protocols/meb.md, "The
supervisor's image").

    python3 meb_student_server.py BUS PORT_FILE [--id N] [--bug BUG]...

It polls slave N (1) on BUS (a serial device or pseudo-terminal, 115200
baud) for its inputs (EA 00-05) every 20 ms, listens on a free port on
127.0.0.1 and writes the port to PORT_FILE. Each --bug plants one mistake
students make, so that `twin check server` can be held to finding it and
nothing else:

  one-client-at-a-time   serves a client until it leaves; the next waits
  write-wrong-block      forwards a client's SA write to the bus as VA
"""
import os
import queue
import socket
import sys
import threading
import time

import serial

SIZES = {"EA": 6, "ED": 1, "FA": 2, "FD": 1, "SA": 1, "SD": 2, "VA": 2, "VD": 1}
READS = {"EA", "ED", "FA", "FD"}


def fcs(text):
    x = 0
    for c in text.encode():
        x ^= c
    return x


def frame(body):
    return "%s%02X*\n" % (body, fcs(body))


def parse(line):
    """(id, cmd, addr, cnt, data) of a well-formed frame's text, or None."""
    line = line.rstrip("\r\n")
    if not line.startswith("@") or not line.endswith("*") or len(line) < 12:
        return None
    body, check = line[:-3], line[-3:-1]
    try:
        ident, addr, cnt = int(body[1:3]), int(body[5:7], 16), int(body[7:9])
        given = int(check, 16)
        rest = body[9:]
        if len(rest) % 4:
            return None
        data = [int(rest[i : i + 4], 16) for i in range(0, len(rest), 4)]
    except ValueError:
        return None
    cmd = body[3:5]
    if not cmd.isalpha() or given != fcs(body):
        return None
    return ident, cmd, addr, cnt, data


class Supervisor:
    def __init__(self, bus, ident, bugs):
        self.port = serial.Serial(bus, 115200, timeout=0.01)
        self.id = ident
        self.bugs = bugs
        self.inputs = None
        self.lock = threading.Lock()
        self.writes = queue.Queue()

    def exchange(self, text):
        """Sends one request; its reply's text, or None after 100 ms (twice)."""
        for _ in range(2):
            self.port.reset_input_buffer()
            self.port.write(text.encode())
            got = b""
            until = time.monotonic() + 0.1
            while time.monotonic() < until:
                got += self.port.read(64)
                if b"\n" in got:
                    line = got[: got.index(b"\n") + 1]
                    return line[line.rfind(b"@") :].decode(errors="replace")
        return None

    def master(self):
        while True:
            try:
                request, done = self.writes.get_nowait()
                done.append(self.exchange(request))
                continue
            except queue.Empty:
                pass
            reply = self.exchange(frame("@%02dEA0006" % self.id))
            parsed = reply and parse(reply)
            if parsed and parsed[1] == "EA" and len(parsed[4]) == 6:
                with self.lock:
                    self.inputs = parsed[4]
            time.sleep(0.02)

    def forward(self, body):
        done = []
        self.writes.put((frame(body), done))
        until = time.monotonic() + 1.0
        while not done and time.monotonic() < until:
            time.sleep(0.002)
        return done[0] if done else None

    def answer(self, line):
        """The reply to one request line, or None."""
        parsed = parse(line)
        if parsed is None:
            return None
        ident, cmd, addr, cnt, data = parsed
        if ident == 0 or cmd == "ER":
            return None
        error = lambda code: frame("@%02dER%02X01%04X" % (ident, addr, code))
        if cmd in READS and data or cmd in SIZES and cmd not in READS and cnt and not data:
            return None
        if ident != self.id:
            return error(2)
        if cmd not in SIZES:
            return error(1)
        if cnt == 0:
            return error(3)
        head = "@%02d%s%02X%02d" % (ident, cmd, addr, cnt)
        if cmd in READS:
            if cmd != "EA" or addr + cnt > 6:
                return error(2)
            with self.lock:
                inputs = self.inputs
            if inputs is None:
                return error(4)
            return frame(head + "".join("%04X" % w for w in inputs[addr : addr + cnt]))
        sent = cmd
        if cmd == "SA" and "write-wrong-block" in self.bugs:
            sent = "VA"
        reply = self.forward("@%02d%s%02X%02d" % (ident, sent, addr, cnt) + "".join("%04X" % w for w in data))
        slave = reply and parse(reply)
        if not slave:
            return error(4)
        if slave[1] == "ER":
            return error(slave[4][0] if slave[4] else 4)
        return frame(head)

    def serve(self, conn):
        buf = b""
        with conn:
            while True:
                try:
                    got = conn.recv(1024)
                except OSError:
                    return
                if not got:
                    return
                buf += got
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    text = line.decode(errors="replace")
                    if "@" in text:
                        text = text[text.rfind("@") :]
                    reply = self.answer(text + "\n")
                    if reply:
                        conn.sendall(reply.encode())


def main():
    args = sys.argv[1:]
    bus, port_file = args[0], args[1]
    ident, bugs = 1, set()
    i = 2
    while i < len(args):
        if args[i] == "--id":
            ident = int(args[i + 1])
        elif args[i] == "--bug":
            bugs.add(args[i + 1])
        i += 2
    supervisor = Supervisor(bus, ident, bugs)
    threading.Thread(target=supervisor.master, daemon=True).start()
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    with open(port_file + ".tmp", "w") as f:
        f.write(str(listener.getsockname()[1]))
    os.replace(port_file + ".tmp", port_file)
    while True:
        conn, _ = listener.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if "one-client-at-a-time" in bugs:
            supervisor.serve(conn)
        else:
            threading.Thread(target=supervisor.serve, args=(conn,), daemon=True).start()


if __name__ == "__main__":
    main()
