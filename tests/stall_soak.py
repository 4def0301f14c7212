#!/usr/bin/env python3
"""Stop `twin supervise` (SIGSTOP, SIGCONT) again and again while it polls
`twin serve` over a `twin vsp` pair, and read from its recording what every
request waited for.

The supervisor polls every --poll-ms with a --timeout-ms reply timeout; the
script stops it --stalls times, each for --stop-ms, at random moments
(--gap-ms apart, seeded by --seed so a run's schedule can be repeated). A
stall is time the session's clock slips, never time a request waited, so in
the recording's bus frames (`/link/bus/frames`, read with `twin export`):

  early  a request sent again (the same frame, no reply between) sooner than
         the reply timeout after its first copy left;
  late   a request retried, or answered, more than the timeout and 10 ms
         (the catch-up and the engine's own pass) after it left.

It prints the counts, the first few of each, the supervisor's timeouts and
the real time lost. A busy machine delays the twin's own threads and the
slave too: run it on a quiet machine for the supervisor's own figures, and
beside a build to see what load does. Exit status 1 if any request was
early, 2 if none was early but some were late.

    cargo build -p twin
    python3 tests/stall_soak.py --twin target/debug/twin --stalls 800 \\
        --stop-ms 50 --gap-ms 20 60 --seed 7

Needs only Python 3's standard library (and `twin export`).
"""

import argparse
import csv
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time


def wait_for(paths, within=10.0):
    deadline = time.monotonic() + within
    while not all(os.path.exists(p) for p in paths):
        if time.monotonic() > deadline:
            sys.exit(f"twin vsp made no pair at {paths} within {within:.0f} s")
        time.sleep(0.05)


def judge(frames, timeout_s, longest_s):
    """Early retries and late waits, as (start, text) lines."""
    early, late = [], []
    for (t0, from0, text0), (t1, from1, text1) in zip(frames, frames[1:]):
        if from0 != "twin":
            continue
        waited = t1 - t0
        if from1 != "twin" and waited > longest_s:
            late.append(f"{text0} at {t0:.4f} s answered {waited * 1e3:.1f} ms later")
        if from1 == "twin" and text1 == text0:
            if waited < timeout_s:
                early.append(f"{text0} at {t0:.4f} s retried {waited * 1e3:.1f} ms later")
            elif waited > longest_s:
                late.append(f"{text0} at {t0:.4f} s retried {waited * 1e3:.1f} ms later")
    return early, late


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--twin", default=shutil.which("twin") or "twin", help="the twin binary")
    ap.add_argument("--stalls", type=int, default=60, help="how many stops [60]")
    ap.add_argument("--stop-ms", type=float, default=100, help="each stop's length [100]")
    ap.add_argument("--gap-ms", type=float, nargs=2, default=[100, 250], metavar=("MIN", "MAX"),
                    help="time between stops, drawn evenly [100 250]")
    ap.add_argument("--seed", type=int, default=1, help="the stops' schedule [1]")
    ap.add_argument("--poll-ms", type=float, default=2, help="the supervisor's poll period [2]")
    ap.add_argument("--timeout-ms", type=float, default=30, help="its reply timeout [30]")
    ap.add_argument("--keep", action="store_true", help="keep the recording and its CSV files")
    args = ap.parse_args()

    work = tempfile.mkdtemp(prefix="twin-stall-")
    a, b = os.path.join(work, "ttyA"), os.path.join(work, "ttyB")
    out = os.path.join(work, "supervise.mcap")
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    vsp = subprocess.Popen([args.twin, "vsp", a, b], **quiet)
    serve = supervise = None
    try:
        wait_for([a, b])
        serve = subprocess.Popen([args.twin, "serve", "--meb", b, "--quiet", "--no-record",
                                  "--status-every", "0"], **quiet)
        time.sleep(1.0)
        supervise = subprocess.Popen(
            [args.twin, "supervise", "--meb", a, "--no-server", "--set-point", "1000",
             "--poll-ms", str(args.poll_ms), "--timeout-ms", str(args.timeout_ms), "--quiet",
             "--status-every", "0", "--out", out],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        time.sleep(1.0)
        rng = random.Random(args.seed)
        for _ in range(args.stalls):
            time.sleep(rng.uniform(*args.gap_ms) / 1e3)
            os.kill(supervise.pid, signal.SIGSTOP)
            time.sleep(args.stop_ms / 1e3)
            os.kill(supervise.pid, signal.SIGCONT)
        time.sleep(0.5)
        supervise.send_signal(signal.SIGTERM)
        printed, _ = supervise.communicate(timeout=30)
    finally:
        for p in (supervise, serve, vsp):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGCONT if p is supervise else signal.SIGTERM)
                p.send_signal(signal.SIGTERM)
                p.wait(timeout=30)

    tables = os.path.join(work, "csv")
    subprocess.run([args.twin, "export", "--csv", tables, out], check=True, **quiet)
    with open(os.path.join(tables, "link_bus_frames.csv"), newline="") as f:
        frames = [(float(r["start_s"]), r["from"], r["text"].strip()) for r in csv.DictReader(f)]
    timeout_s = args.timeout_ms / 1e3
    early, late = judge(frames, timeout_s, timeout_s + 0.010)
    print(f"{args.stalls} stops of {args.stop_ms:.0f} ms, {len(frames)} frames: "
          f"{len(early)} early, {len(late)} late")
    for line in early[:10]:
        print("  early:", line)
    for line in late[:10]:
        print("  late: ", line)
    for line in printed.splitlines():
        if "timeouts" in line or "real time lost" in line:
            print(" ", line.strip())
    if args.keep:
        print(f"kept: {out} and {tables}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    return 1 if early else 2 if late else 0


if __name__ == "__main__":
    sys.exit(main())
