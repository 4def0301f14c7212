"""A student's MEB slave, as a student of the M3CVME lab would write one,
outside the twin's code: the module controller's side of the MEB page
(docs/protocols/meb.md) with the default map, over TCP, one client at a time.

    python3 meb_student_slave.py PORT_FILE [--id N] [--pty] [--bug BUG]...

It listens on a free port on 127.0.0.1 and writes the port to PORT_FILE;
with --pty it opens a pseudo-terminal instead (a board on a USB serial
adapter, as the checker sees it) and writes the path of its far end.
Each --bug plants one mistake students make, so that `twin check` can be
held to finding it and nothing else:

  answers-bad-fcs     answers a frame whose FCS is wrong
  fcs-without-at      computes its replies' FCS without the @
  answers-broadcast   answers a broadcast write
  no-resync           does not restart a frame at an @ (a partial frame spoils the next)
  wrong-error-code    answers an address out of range with error 03, not 02
  slow                answers every request 150 ms after it came (a sketch
                      that does too much between its reads of the port)
  hangs-up-after N    answers N requests, then closes the connection when
                      the next one comes (a program that crashes mid-run)
"""
import socket
import sys
import time

SIZES = {"EA": 6, "ED": 1, "FA": 2, "FD": 1, "SA": 1, "SD": 2, "VA": 2, "VD": 1}
READS = {"EA", "ED", "FA", "FD"}
LIMITS = {"SA": [4095], "SD": [0x1F, 0x01], "VA": [4095, 1000], "VD": [0x1]}


def fcs(text, bugs):
    if "fcs-without-at" in bugs:
        text = text[1:]
    x = 0
    for c in text.encode():
        x ^= c
    return x


def frame(body, bugs):
    return ("%s%02X*\n" % (body, fcs(body, bugs))).encode()


class Slave:
    def __init__(self, ident, bugs, answers=None):
        self.id = ident
        self.bugs = bugs
        # How many more requests it answers before it hangs up (None: all).
        self.answers = answers
        self.words = {
            "EA": [0xBD6, 0x800, 0xD05, 0, 0, 0xCD3],
            "ED": [0x1],
            "FA": [1000, 0],
            "FD": [0],
            "SA": [0],
            "SD": [0x1F, 0x01],
            "VA": [1933, 100],
            "VD": [1],
        }

    def handle(self, text):
        """The reply to one frame's text (from @ to before *), or None."""
        if len(text) < 11:
            return None
        body, check = text[:-2], text[-2:]
        try:
            ident, cnt = int(body[1:3]), int(body[7:9])
            addr = int(body[5:7], 16)
            given = int(check, 16)
            data = [int(body[9 + 4 * i : 13 + 4 * i], 16) for i in range((len(body) - 9) // 4)]
        except ValueError:
            self.words["FA"][1] += 1
            return None
        cmd = body[3:5]
        if not cmd.isalpha() or (len(body) - 9) % 4:
            return None
        if given != fcs(body, set()) and "answers-bad-fcs" not in self.bugs:
            self.words["FA"][1] += 1
            return None
        if ident not in (0, self.id):
            return None
        if cmd == "ER" or (cmd in READS and data) or (cmd not in READS and cmd in SIZES and cnt and not data):
            return None
        if ident == 0 and (cmd in READS or "answers-broadcast" not in self.bugs):
            if cmd not in READS and cmd in SIZES:
                self.apply(cmd, addr, cnt, data)
            return None
        head = "@%02d%s%02X%02d" % (self.id, cmd, addr, cnt)
        error = lambda code: "@%02dER%02X01%04X" % (self.id, addr, code)
        if cmd not in SIZES:
            return error(1)
        if cnt == 0:
            return error(3)
        if addr + cnt > SIZES[cmd]:
            return error(3 if "wrong-error-code" in self.bugs else 2)
        if cmd in READS:
            return head + "".join("%04X" % w for w in self.words[cmd][addr : addr + cnt])
        if any(v > LIMITS[cmd][addr + i] and cmd in ("SA", "VA") for i, v in enumerate(data)):
            return error(3)
        if any(v & ~LIMITS[cmd][addr + i] for i, v in enumerate(data) if cmd in ("SD", "VD")):
            return error(3)
        if cmd == "VA" and any(addr + i == 1 and v == 0 for i, v in enumerate(data)):
            return error(3)
        self.apply(cmd, addr, cnt, data)
        return head

    def apply(self, cmd, addr, cnt, data):
        for i, v in enumerate(data[:cnt]):
            if addr + i < SIZES[cmd]:
                self.words[cmd][addr + i] = v


def serve(conn, slave):
    buf = ""
    while True:
        chunk = conn.recv(1024)
        if not chunk:
            return
        for c in chunk.decode("latin-1"):
            if c == "@" and "no-resync" not in slave.bugs:
                buf = "@"
                continue
            if not buf:
                if c == "@":
                    buf = "@"
                continue
            buf += c
            if buf.endswith("*\n") or buf.endswith("*\r\n"):
                text = buf[: buf.rindex("*")]
                buf = ""
                if slave.answers == 0:
                    return  # hangs up on this request
                reply = slave.handle(text)
                if reply is not None:
                    if "slow" in slave.bugs:
                        time.sleep(0.150)
                    conn.sendall(frame(reply, slave.bugs))
                    if slave.answers is not None:
                        slave.answers -= 1


class Pty:
    """A pseudo-terminal's master end, used as the socket is."""

    def __init__(self, fd):
        self.fd = fd

    def recv(self, n):
        import os

        try:
            return os.read(self.fd, n)
        except OSError:
            return b""  # the checker closed its end

    def sendall(self, data):
        import os

        while data:
            data = data[os.write(self.fd, data) :]


def main():
    args = sys.argv[1:]
    port_file, ident, bugs, answers, pty = args[0], 1, set(), None, False
    i = 1
    while i < len(args):
        if args[i] == "--id":
            ident = int(args[i + 1])
        elif args[i] == "--pty":
            pty = True
            i += 1
            continue
        elif args[i] == "--bug" and args[i + 1] == "hangs-up-after":
            answers = int(args[i + 2])
            i += 1
        elif args[i] == "--bug":
            bugs.add(args[i + 1])
        i += 2
    if pty:
        return serve_pty(port_file, ident, bugs, answers)
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    with open(port_file + ".tmp", "w") as f:
        f.write(str(server.getsockname()[1]))
    import os

    os.rename(port_file + ".tmp", port_file)
    slave = Slave(ident, bugs, answers)
    while True:
        conn, _ = server.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            serve(conn, slave)
        except OSError:
            pass  # the checker hung up mid-exchange
        finally:
            conn.close()


def serve_pty(path_file, ident, bugs, answers):
    """One run on a pseudo-terminal; hanging up closes it, as a board
    unplugged takes its serial port away."""
    import os
    import tty

    master, slave_fd = os.openpty()
    tty.setraw(slave_fd)
    with open(path_file + ".tmp", "w") as f:
        f.write(os.ttyname(slave_fd))
    os.rename(path_file + ".tmp", path_file)
    try:
        serve(Pty(master), Slave(ident, bugs, answers))
    finally:
        os.close(master)
        os.close(slave_fd)


if __name__ == "__main__":
    main()
