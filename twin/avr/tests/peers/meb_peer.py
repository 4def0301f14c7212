"""What the MEB test masters beside it share (meb_latency.py, meb_burst.py),
written from docs/protocols/meb.md alone: a read request's line with its FCS,
a TCP connection to the server with Nagle off, so a request leaves as it is
written, and the bytes it sends.
"""
import socket

SLAVE = 1
WAIT_S = 3.0


def fcs(data: bytes) -> int:
    x = 0
    for b in data:
        x ^= b
    return x


def frame(cmd, addr, cnt):
    body = "@%02d%s%02X%02d" % (SLAVE, cmd, addr, cnt)
    return (body + "%02X*\n" % fcs(body.encode())).encode()


def connect(host, port):
    sock = socket.create_connection((host, port), timeout=WAIT_S)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def received(sock):
    """The next bytes the server sends; b"" once it has been quiet for
    WAIT_S or has closed."""
    try:
        return sock.recv(4096)
    except socket.timeout:
        return b""
