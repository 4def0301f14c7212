#!/usr/bin/env python3
"""A student's own MEB-TCP client, the smallest one: read EA 00-05 once.

Usage: python3 meb_client.py [HOST [PORT]]   (default 127.0.0.1 5701: twin supervise)
Works against `twin supervise --listen`, `twin serve --meb tcp://...`, or any
server that speaks MEB as docs/protocols/meb.md says.
"""
import socket
import sys


def frame(slave, cmd, addr, cnt, words=()):
    """@ ID CMD ADDR CNT DATA FCS * LF, FCS the XOR of every byte before it."""
    body = f"@{slave:02d}{cmd}{addr:02X}{cnt:02d}" + "".join(f"{w:04X}" for w in words)
    fcs = 0
    for b in body.encode():
        fcs ^= b
    return f"{body}{fcs:02X}*\n".encode()


host = sys.argv[1] if len(sys.argv) > 1 else "127.0.0.1"
port = int(sys.argv[2]) if len(sys.argv) > 2 else 5701
with socket.create_connection((host, port), timeout=1.0) as s:
    s.sendall(frame(1, "EA", 0x00, 6))
    reply = b""
    while not reply.endswith(b"\n"):
        chunk = s.recv(512)
        if not chunk:
            sys.exit("the server closed the connection")
        reply += chunk
text = reply.decode().strip()
if text[3:5] == "ER":
    sys.exit(f"error reply {text}: code {int(text[9:13], 16):02d}")
cnt = int(text[7:9])
words = [int(text[9 + 4 * i:13 + 4 * i], 16) for i in range(cnt)]
for name, word in zip(["V2", "I", "V1", "RPM_M", "RPM_L", "LDR"], words):
    print(f"{name:6} {word:5}")
