"""An MEB master over TCP that does not wait for each reply: it writes
BURST read requests in one go (different blocks, addresses and counts), then
reads until every reply has come, and checks they answer the requests in
order. Written from docs/protocols/meb.md alone.

    python3 meb_burst.py HOST PORT ROUNDS BURST

Prints one JSON object: requests, replies, replies that answered another
request (out of order or garbled), and the slowest round in ms.
"""
import json
import sys
import time

from meb_peer import SLAVE, WAIT_S, connect, fcs, frame, received


def main():
    host, port, rounds, burst = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    sock = connect(host, port)
    kinds = [("EA", 0, 3), ("ED", 0, 1), ("FA", 0, 2), ("EA", 1, 2), ("FD", 0, 1)]
    requests = replies = wrong = 0
    slowest = 0.0
    buf = b""
    for r in range(rounds):
        asked = [kinds[(r + i) % len(kinds)] for i in range(burst)]
        start = time.monotonic()
        sock.sendall(b"".join(frame(*k) for k in asked))
        requests += len(asked)
        got = []
        deadline = start + WAIT_S
        while len(got) < len(asked) and time.monotonic() < deadline:
            while b"\n" in buf and len(got) < len(asked):
                line, buf = buf.split(b"\n", 1)
                got.append(line + b"\n")
            if len(got) >= len(asked):
                break
            chunk = received(sock)
            if not chunk:
                break
            buf += chunk
        slowest = max(slowest, (time.monotonic() - start) * 1000)
        replies += len(got)
        for (cmd, addr, cnt), reply in zip(asked, got):
            head = "@%02d%s%02X%02d" % (SLAVE, cmd, addr, cnt)
            if not reply.startswith(head.encode()) or fcs(reply[:-4]) != int(reply[-4:-2], 16):
                wrong += 1
    print(json.dumps({"requests": requests, "replies": replies, "wrong": wrong, "slowest_ms": round(slowest, 1)}))


main()
