#!/usr/bin/env python3
"""A master's raw view of one exchange: sends one request (hex) over TCP
(tcp://HOST:PORT) or a serial device or pseudo-terminal (a path), then
prints every chunk the slave's writes bring, one line of hex each, until
WANT bytes came or DEADLINE seconds passed. Nothing is decoded: the test
reads the bytes on the wire, junk and split replies as they came."""

import os
import select
import socket
import sys
import termios
import time
import tty


def main():
    link, request, want, deadline = sys.argv[1], bytes.fromhex(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
    end = time.monotonic() + deadline
    if link.startswith("tcp://"):
        host, port = link[len("tcp://"):].rsplit(":", 1)
        s = socket.create_connection((host, int(port)), timeout=deadline)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.sendall(request)
        fd = s.fileno()
        read = lambda: s.recv(4096)
    else:
        fd = os.open(link, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        termios.tcflush(fd, termios.TCIOFLUSH)
        os.write(fd, request)
        read = lambda: os.read(fd, 4096)
    got = 0
    while got < want:
        left = end - time.monotonic()
        if left <= 0:
            break
        ready, _, _ = select.select([fd], [], [], left)
        if not ready:
            break
        chunk = read()
        if not chunk:
            break
        got += len(chunk)
        print(chunk.hex(), flush=True)


if __name__ == "__main__":
    main()
