#!/usr/bin/env python3
"""What careless or hostile clients do to `twin serve`'s TCP links.

Usage: python3 twin/cli/bench/abuse_probe.py TWIN WHAT [once]
  TWIN  the twin binary (target/release/twin or target/debug/twin)
  WHAT  crowd      200 clients connect at once, then each sends an MEB request
                   (--max-clients 8): how many are served, refused (closed),
                   or left with neither within 2 s
        stray      8 clients send a byte outside any frame ("0") every 0.5 s;
                   20 newcomers over 40 s ask an MEB request each
        slowloris  100 clients hold half a frame (MEB "@01EA", Modbus TCP five
                   header bytes), an MEB one adding a byte a second; each
                   reconnects as soon as it is closed ("once": it does not);
                   17 newcomers ask on each link, 0.3 s apart
Each newcomer's fate is `served` (its reply), `closed` (closed without one:
refused) or `nothing` (neither within 2 s: kept waiting). The server's own
lines go to abuse_probe_serve.log in the working folder.
"""
import re
import socket
import subprocess
import sys
import threading
import time

TWIN = sys.argv[1]
WHAT = sys.argv[2]
ONCE = len(sys.argv) > 3 and sys.argv[3] == "once"


def meb(body):
    fcs = 0
    for b in body.encode():
        fcs ^= b
    return f"{body}{fcs:02X}*\n".encode()


MEB_REQ = meb("@01EA0001")
MODBUS_REQ = bytes([0, 1, 0, 0, 0, 6, 1, 4, 0, 0, 0, 10])


def start(args):
    """twin serve with `args`; its links' ports by protocol."""
    p = subprocess.Popen(
        [TWIN, "serve", "--no-record", "--quiet", "--status-every", "0"] + args,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    links = {}
    for line in p.stdout:
        m = re.search(r"(meb|modbus-tcp)\s+tcp://127.0.0.1:(\d+)", line)
        if m:
            links[m.group(1)] = int(m.group(2))
        if line.strip() == "ready":
            break
    log = open("abuse_probe_serve.log", "w")
    threading.Thread(target=lambda: [log.write(l) for l in p.stdout], daemon=True).start()
    return p, links


def ask(port, request, expect, wait=2.0):
    try:
        s = socket.create_connection(("127.0.0.1", port), timeout=wait)
    except OSError:
        return "closed"
    s.settimeout(wait)
    try:
        s.sendall(request)
        got = s.recv(100)
        return "served" if got.startswith(expect) else "closed"
    except socket.timeout:
        return "nothing"
    except OSError:
        return "closed"
    finally:
        s.close()


def tally(fates):
    return {k: fates.count(k) for k in ("served", "closed", "nothing")}


def crowd(n=200):
    p, links = start(["--meb", "tcp://127.0.0.1:0"])
    port = links["meb"]
    fates = [None] * n
    barrier = threading.Barrier(n)
    done = threading.Event()

    def one(i):
        try:
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
        except OSError:
            fates[i] = "closed"
            barrier.wait()
            return
        barrier.wait()
        s.settimeout(2.0)
        try:
            s.sendall(MEB_REQ)
            got = s.recv(100)
            fates[i] = "served" if got.startswith(b"@01EA0001") else "closed"
        except socket.timeout:
            fates[i] = "nothing"
        except OSError:
            fates[i] = "closed"
        done.wait(5)
        s.close()

    threads = [threading.Thread(target=one, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    time.sleep(4)
    done.set()
    for t in threads:
        t.join()
    p.terminate()
    p.wait()
    print(f"crowd of {n} at once, --max-clients 8:", tally(fates))


def stray(n=8, seconds=40, newcomers=20):
    p, links = start(["--meb", "tcp://127.0.0.1:0"])
    port = links["meb"]
    socks = [socket.create_connection(("127.0.0.1", port)) for _ in range(n)]
    stop = time.time() + seconds

    def junk():
        while time.time() < stop:
            for s in socks:
                try:
                    s.send(b"0")
                except OSError:
                    pass
            time.sleep(0.5)

    threading.Thread(target=junk, daemon=True).start()
    time.sleep(0.5)
    fates = []
    for _ in range(newcomers):
        fates.append(ask(port, MEB_REQ, b"@01EA0001"))
        time.sleep(max(0, seconds / newcomers - 0.1))
    p.terminate()
    p.wait()
    print(f"{n} stray-byte clients, {newcomers} newcomers over {seconds} s:", tally(fates))


def slowloris(n=100, newcomers=17, seconds=30):
    p, links = start(["--meb", "tcp://127.0.0.1:0", "--modbus", "tcp://127.0.0.1:0"])
    stop = time.time() + seconds

    def holder(port, first):
        while time.time() < stop:
            try:
                s = socket.create_connection(("127.0.0.1", port), timeout=2)
                s.send(first)
                while time.time() < stop:
                    time.sleep(1)
                    if first.startswith(b"@"):
                        s.send(b"0")  # fails once the server has closed it
                        continue
                    try:
                        if s.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b"":
                            break  # closed by the server
                    except BlockingIOError:
                        pass
            except OSError:
                time.sleep(0.05)
            if ONCE:
                return

    for k in range(n):
        port, first = ((links["meb"], b"@01EA") if k % 2 == 0
                       else (links["modbus-tcp"], MODBUS_REQ[:5]))
        threading.Thread(target=holder, args=(port, first), daemon=True).start()
    time.sleep(2)
    meb_fates, modbus_fates = [], []
    for _ in range(newcomers):
        meb_fates.append(ask(links["meb"], MEB_REQ, b"@01EA0001"))
        modbus_fates.append(ask(links["modbus-tcp"], MODBUS_REQ, b"\x00\x01"))
        time.sleep(0.3)
    p.terminate()
    p.wait()
    how = "once each" if ONCE else "reconnecting when closed"
    print(f"{n} slowloris clients ({how}); MEB newcomers:", tally(meb_fates),
          "Modbus newcomers:", tally(modbus_fates))


{"crowd": crowd, "stray": stray, "slowloris": slowloris}[WHAT]()
