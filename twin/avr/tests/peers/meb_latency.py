"""An MEB master over TCP that sends one read at a time and times each
reply: from the request's last byte written to the reply's whole line read.
Written from docs/protocols/meb.md alone; measures how soon a server (a
sketch in `twin-avr serve`) answers.

    python3 meb_latency.py HOST PORT REQUESTS

Prints one JSON object: requests, replies, wrong replies, and the reply
latency's p50, p99 and max in microseconds.
"""
import json
import sys
import time

from meb_peer import SLAVE, connect, frame, received


def main():
    host, port, count = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    sock = connect(host, port)
    kinds = [("EA", 0, 3), ("ED", 0, 1), ("FA", 0, 2)]
    latencies = []
    wrong = 0
    buf = b""
    for n in range(count):
        cmd, addr, cnt = kinds[n % len(kinds)]
        start = time.perf_counter()
        sock.sendall(frame(cmd, addr, cnt))
        while b"\n" not in buf:
            chunk = received(sock)
            if not chunk:
                break
            buf += chunk
        if b"\n" not in buf:
            break
        line, buf = buf.split(b"\n", 1)
        latencies.append((time.perf_counter() - start) * 1e6)
        if not line.startswith(("@%02d%s" % (SLAVE, cmd)).encode()):
            wrong += 1
        # Requests spread out as a polling master's, not back to back.
        time.sleep(0.002 + 0.001 * (n % 7) / 7)
    latencies.sort()
    q = lambda p: latencies[min(len(latencies) - 1, int(p * len(latencies)))] if latencies else None
    print(json.dumps({
        "requests": count,
        "replies": len(latencies),
        "wrong": wrong,
        "p50_us": q(0.5),
        "p99_us": q(0.99),
        "max_us": latencies[-1] if latencies else None,
    }))


if __name__ == "__main__":
    main()
