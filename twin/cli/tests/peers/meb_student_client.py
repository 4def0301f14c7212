"""A student's remote client (TCP CLI in the M3CVME paper), as a student of
the M3CVME lab would write one, outside the twin's code, following the
checklist `twin check client` prints: read the inputs, set VEL to half,
switch the module on, read again until the server answers an error, read
again until it hangs up, connect again and read.

    python3 meb_student_client.py HOST:PORT [--id N] [--bug BUG]...

It prints what a user would see. Each --bug plants one mistake students
make, so that `twin check client` can be held to finding it:

  writes-wrong-block   writes VEL to VA 00 instead of SA 00
"""
import socket
import sys
import time

NAMES = ["V2", "I", "V1", "RPM_M", "RPM_L", "LDR"]


def frame(body):
    x = 0
    for c in body.encode():
        x ^= c
    return ("%s%02X*\n" % (body, x)).encode()


class Client:
    def __init__(self, addr, ident):
        self.addr = addr
        self.id = ident
        self.connect()

    def connect(self):
        host, port = self.addr.rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=5)
        self.sock.settimeout(5)
        self.buf = b""

    def request(self, body):
        """The reply's text, or None when the server hung up."""
        self.sock.sendall(frame("@%02d%s" % (self.id, body)))
        while b"\n" not in self.buf:
            try:
                got = self.sock.recv(512)
            except OSError:
                return None
            if not got:
                return None
            self.buf += got
        line, self.buf = self.buf.split(b"\n", 1)
        return line.decode()

    def read_inputs(self):
        reply = self.request("EA0006")
        if reply is None:
            print("the server hung up")
            return None
        if reply[3:5] == "ER":
            print("error %s from the server" % reply[9:13])
            return "error"
        words = [int(reply[9 + 4 * i : 13 + 4 * i], 16) for i in range(6)]
        print("  ".join("%s %d" % (n, w) for n, w in zip(NAMES, words)))
        return words


def main():
    args = sys.argv[1:]
    addr, ident, bugs = args[0], 1, set()
    i = 1
    while i < len(args):
        if args[i] == "--id":
            ident = int(args[i + 1])
        elif args[i] == "--bug":
            bugs.add(args[i + 1])
        i += 2
    client = Client(addr, ident)
    client.read_inputs()
    vel_block = "VA" if "writes-wrong-block" in bugs else "SA"
    print("VEL:", client.request("%s00010800" % vel_block))
    print("EN on:", client.request("SD0001001E"))
    # The checklist's faults come when the twin has seen the steps before:
    # read until each shows, as a user would try again.
    for _ in range(40):
        if client.read_inputs() == "error":
            break
        time.sleep(0.25)
    for _ in range(40):
        if client.read_inputs() is None:
            break
        time.sleep(0.25)
    client.connect()
    client.read_inputs()


if __name__ == "__main__":
    main()
