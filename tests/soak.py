#!/usr/bin/env python3
"""Soak `twin serve` in real time: three masters poll it for as long as asked
and every reply is checked.

  an MEB-TCP master      reads EA (the analog inputs) of module 01
  a Modbus TCP master    reads 10 input registers (FC04) of unit 1
  a Modbus RTU master    on a pseudo-terminal the script opens, FC04 as well

each at --rate requests a second (100 by default), one request in flight at a
time. Every 10 s the server's resident memory (VmRSS) and thread count are
sampled from /proc; the server's own report gives the plant's tick lateness
(per second and over the whole run). At the end the server is stopped with
SIGTERM, as a service manager would, and its recording is deleted unless
--keep is given.

Run it by hand on an idle machine for the real figure (an hour):
    cargo build --release -p twin
    python3 tests/soak.py --twin target/release/twin --seconds 3600
CI runs a 30-second one (twin/cli/tests/it/soak.rs). --json prints the
figures as JSON on the last line. A reply later than 2 s is counted late (a
real master would have timed out and asked again); one still missing after
12 s is lost. The exit status is 1 if any reply was lost or wrong, or the
server stopped on its own.

Needs only Python 3's standard library.
"""

import argparse
import glob
import json
import os
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import tty


# A reply later than this is counted late (a real master would have timed
# out); one not there after GIVE_UP_S is lost. Waiting that long for it keeps
# a late reply from being taken for the next request's.
LATE_S = 2.0
GIVE_UP_S = 12.0


def crc16_modbus(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def meb_frame(body: str) -> bytes:
    fcs = 0
    for c in body.encode():
        fcs ^= c
    return f"{body}{fcs:02X}*\n".encode()


def meb_valid(line: bytes) -> bool:
    # @01EA<data><FCS>*\n : the FCS is the XOR of everything before it.
    if not (line.startswith(b"@01EA") and line.endswith(b"*\n")) or len(line) < 9:
        return False
    body, fcs = line[:-4], line[-4:-2]
    x = 0
    for c in body:
        x ^= c
    return f"{x:02X}".encode() == fcs


class Master:
    """One polling master: counts and times its exchanges."""

    def __init__(self, name: str):
        self.name = name
        self.sent = 0
        self.answered = 0
        self.wrong = 0
        self.lost = 0
        # Answered, but later than a master's usual timeout.
        self.late = 0
        self.latencies_us = []
        self.first_problem = None

    def problem(self, what: str):
        if self.first_problem is None:
            self.first_problem = f"{what} (request {self.sent})"

    def figures(self) -> dict:
        lat = sorted(self.latencies_us)
        pick = lambda q: round(lat[min(len(lat) - 1, int(q * len(lat)))]) if lat else None
        return {
            "sent": self.sent,
            "answered": self.answered,
            "wrong": self.wrong,
            "lost": self.lost,
            "late": self.late,
            "latency_p50_us": pick(0.50),
            "latency_p99_us": pick(0.99),
            "latency_max_us": round(lat[-1]) if lat else None,
            "first_problem": self.first_problem,
        }


def poll(master: Master, exchange, rate: float, stop: threading.Event):
    period = 1.0 / rate
    due = time.monotonic()
    while not stop.is_set():
        master.sent += 1
        started = time.monotonic()
        try:
            verdict = exchange()
        except (socket.timeout, TimeoutError):
            verdict = f"no reply within {GIVE_UP_S:g} s"
        except OSError as e:
            verdict = f"link error: {e}"
        took = time.monotonic() - started
        if verdict is None:
            master.answered += 1
            master.latencies_us.append(took * 1e6)
            if took > LATE_S:
                master.late += 1
                master.problem(f"a reply {took:.2f} s late")
        elif verdict.startswith("no reply") or verdict.startswith("link error"):
            master.lost += 1
            master.problem(verdict)
        else:
            master.wrong += 1
            master.problem(verdict)
        due += period
        pause = due - time.monotonic()
        if pause > 0:
            time.sleep(pause)
        else:
            due = time.monotonic()  # behind: do not burst to catch up


def meb_exchange(addr):
    s = socket.create_connection(addr, timeout=5)
    s.settimeout(GIVE_UP_S)
    request = meb_frame("@01EA0003")
    buf = b""

    def exchange():
        nonlocal buf
        s.sendall(request)
        while b"\n" not in buf:
            chunk = s.recv(4096)
            if not chunk:
                raise OSError("the server closed the connection")
            buf += chunk
        line, _, buf = buf.partition(b"\n")
        line += b"\n"
        return None if meb_valid(line) else f"bad MEB reply {line!r}"

    return exchange


def modbus_tcp_exchange(addr):
    s = socket.create_connection(addr, timeout=5)
    s.settimeout(GIVE_UP_S)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    tid = 0

    def recv_exact(n):
        data = b""
        while len(data) < n:
            chunk = s.recv(n - len(data))
            if not chunk:
                raise OSError("the server closed the connection")
            data += chunk
        return data

    def exchange():
        nonlocal tid
        tid = (tid + 1) & 0xFFFF
        s.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 4, 0, 10))
        head = recv_exact(7)
        got_tid, proto, length, unit = struct.unpack(">HHHB", head)
        pdu = recv_exact(length - 1)
        if got_tid != tid or proto != 0 or unit != 1:
            return f"bad MBAP header {head.hex()}"
        if pdu[:2] != bytes([4, 20]) or len(pdu) != 22:
            return f"bad FC04 reply {pdu.hex()}"
        return None

    return exchange


def rtu_exchange(fd):
    body = bytes([1, 4, 0, 0, 0, 10])
    request = body + struct.pack("<H", crc16_modbus(body))

    def exchange():
        os.write(fd, request)
        reply = b""
        deadline = time.monotonic() + GIVE_UP_S
        while len(reply) < 25:
            left = deadline - time.monotonic()
            if left <= 0:
                return f"no reply within {GIVE_UP_S:g} s" if not reply else f"a cut reply {reply.hex()}"
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                reply += os.read(fd, 25 - len(reply))
        if reply[:3] != bytes([1, 4, 20]):
            return f"bad RTU reply {reply.hex()}"
        if struct.unpack("<H", reply[23:25])[0] != crc16_modbus(reply[:23]):
            return f"bad RTU CRC {reply.hex()}"
        return None

    return exchange


def proc_status(pid: int) -> dict:
    fields = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                key, _, value = line.partition(":")
                fields[key] = value.strip()
    except OSError:
        return {}
    return {
        "rss_mib": round(int(fields.get("VmRSS", "0 kB").split()[0]) / 1024, 1),
        "threads": int(fields.get("Threads", "0")),
    }


LATENESS_SECOND = re.compile(r"tick lateness p99 (\d+) µs, max (\d+) µs")
LATENESS_TOTAL = re.compile(
    r"tick lateness over (\d+) ticks: p50 (\d+) µs, p99 (\d+) µs, p99\.9 (\d+) µs, max (\d+) µs; (\d+) overruns"
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--twin", default=shutil.which("twin") or "twin", help="the twin binary")
    ap.add_argument("--seconds", type=float, default=3600, help="how long to poll [3600]")
    ap.add_argument("--rate", type=float, default=100, help="requests a second per master [100]")
    ap.add_argument("--sample", type=float, default=10, help="seconds between memory samples [10]")
    ap.add_argument("--keep", action="store_true", help="keep the recording")
    ap.add_argument("--no-record", action="store_true",
                    help="serve without recording (to tell the recording's memory from the rest)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON last")
    ap.add_argument("--serve-arg", action="append", default=[], metavar="ARG",
                    help="one more argument for twin serve, e.g. --serve-arg=--rotate-every "
                         "--serve-arg=10m (a service rotates its recording, which bounds its memory)")
    args = ap.parse_args()

    scratch = tempfile.mkdtemp(prefix="twin-soak-")
    master_fd, slave_fd = os.openpty()
    tty.setraw(master_fd)
    tty.setraw(slave_fd)
    pty_path = os.ttyname(slave_fd)
    recording = os.path.join(scratch, "soak.mcap")
    server = subprocess.Popen(
        [args.twin, "serve", "--quiet", *(["--no-record"] if args.no_record else ["--out", recording]),
         "--meb", "tcp://127.0.0.1:0", "--modbus", "tcp://127.0.0.1:0",
         "--modbus-rtu", pty_path, *args.serve_arg],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    links = {}
    for line in server.stdout:
        if line.strip() == "ready":
            break
        words = line.split()
        if len(words) >= 2 and words[1].startswith("tcp://"):
            host, port = words[1][len("tcp://"):].rsplit(":", 1)
            links[words[0]] = (host, int(port))
    else:
        print("twin serve stopped before it was ready:", server.stderr.read(), file=sys.stderr)
        return 1

    seconds_lateness = []
    report = []

    def read_report():
        for line in server.stdout:
            report.append(line)
            m = LATENESS_SECOND.search(line)
            if m:
                seconds_lateness.append((int(m.group(1)), int(m.group(2))))

    threading.Thread(target=read_report, daemon=True).start()

    masters = [Master("meb-tcp"), Master("modbus-tcp"), Master("modbus-rtu-pty")]
    exchanges = [meb_exchange(links["meb"]), modbus_tcp_exchange(links["modbus-tcp"]), rtu_exchange(master_fd)]
    stop = threading.Event()
    pollers = [threading.Thread(target=poll, args=(m, e, args.rate, stop), daemon=True)
               for m, e in zip(masters, exchanges)]
    started = time.monotonic()
    samples = [dict(t_s=0.0, **proc_status(server.pid))]
    for p in pollers:
        p.start()
    stopped_by_itself = False
    while time.monotonic() - started < args.seconds:
        time.sleep(min(args.sample, max(0.0, args.seconds - (time.monotonic() - started))))
        if server.poll() is not None:
            stopped_by_itself = True
            break
        samples.append(dict(t_s=round(time.monotonic() - started, 1), **proc_status(server.pid)))
        last = samples[-1]
        print(f"[{last['t_s']:8.1f} s] RSS {last.get('rss_mib')} MiB, {last.get('threads')} threads, "
              + ", ".join(f"{m.name} {m.answered}/{m.sent}" for m in masters), file=sys.stderr)
    stop.set()
    for p in pollers:
        p.join(timeout=5)
    elapsed = time.monotonic() - started
    if not stopped_by_itself:
        server.send_signal(signal.SIGTERM)
    try:
        server.wait(timeout=60)
    except subprocess.TimeoutExpired:
        server.kill()
        server.wait()
    time.sleep(0.2)
    total = None
    for line in report:
        m = LATENESS_TOTAL.search(line)
        if m:
            total = dict(zip(["ticks", "p50_us", "p99_us", "p999_us", "max_us", "overruns"],
                             map(int, m.groups())))
    # The first sample is taken before the masters connect (each TCP client
    # has a thread of its own); flatness is judged from the next one on.
    before = samples[0]
    during = samples[1:] or samples
    rss = [s["rss_mib"] for s in during if "rss_mib" in s]
    threads = [s["threads"] for s in during if "threads" in s]
    half = len(rss) // 2
    recordings = sorted(glob.glob(os.path.join(scratch, "*.mcap")))
    figures = {
        "seconds": round(elapsed, 1),
        "rate_per_master": args.rate,
        "masters": {m.name: m.figures() for m in masters},
        "before_clients": before,
        "rss_mib": {"first": rss[0] if rss else None, "last": rss[-1] if rss else None,
                    "max": max(rss) if rss else None,
                    # Flat: the second half grows no more than the first settled.
                    "max_first_half": max(rss[:half + 1]) if rss else None},
        "threads": {"first": threads[0] if threads else None, "last": threads[-1] if threads else None,
                    "max": max(threads) if threads else None},
        "samples": samples,
        "tick_lateness_total": total,
        "tick_lateness_worst_second_p99_us": max((p for p, _ in seconds_lateness), default=None),
        "server_exit": server.returncode,
        "server_stopped_by_itself": stopped_by_itself,
        # With --rotate-every the session's files are soak.mcap and soak-START.mcap beside it.
        "recording_files": len(recordings),
        "recording_bytes": sum(os.path.getsize(f) for f in recordings),
    }
    if args.keep:
        figures["recording"] = recording
    else:
        shutil.rmtree(scratch, ignore_errors=True)

    print(f"twin soak: {figures['seconds']} s, {args.rate:g} requests/s per master")
    for m in masters:
        f = m.figures()
        print(f"  {m.name:15} {f['answered']:9} of {f['sent']:9} answered ({f['late']} over {LATE_S:g} s late), {f['lost']} lost, {f['wrong']} wrong;"
              f" latency p50 {f['latency_p50_us']} µs, p99 {f['latency_p99_us']} µs, max {f['latency_max_us']} µs"
              + (f"; first problem: {f['first_problem']}" if f["first_problem"] else ""))
    r, t = figures["rss_mib"], figures["threads"]
    print(f"  RSS {r['first']} -> {r['last']} MiB (max {r['max']}), threads {t['first']} -> {t['last']} (max {t['max']});"
          f" before the masters connected: {before.get('rss_mib')} MiB, {before.get('threads')} threads")
    if recordings:
        print(f"  recording: {len(recordings)} file(s), {figures['recording_bytes'] / 1e6:.1f} MB")
    if total:
        print(f"  tick lateness over {total['ticks']} ticks: p50 {total['p50_us']} µs, p99 {total['p99_us']} µs,"
              f" p99.9 {total['p999_us']} µs, max {total['max_us']} µs; {total['overruns']} overruns;"
              f" worst second's p99 {figures['tick_lateness_worst_second_p99_us']} µs")
    if args.json:
        print(json.dumps(figures))
    bad = stopped_by_itself or any(m.lost or m.wrong for m in masters)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
