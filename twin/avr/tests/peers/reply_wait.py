"""How long a sketch's replies waited in `twin-avr serve`, from a session's
recording exported with `twin export --csv DIR REC.mcap`: for each reply,
from the moment the sketch's line went quiet after it (its last byte's end
plus two characters, when the server takes a frame as whole) to the moment
the reply left on the link; and for each request, how much earlier than it
came on the link its last byte reached the sketch (0 when never early).

    python3 reply_wait.py DIR [DIR ...]

Prints a line per folder: p50, p90 and p99 of both, in microseconds.
"""
import csv
import glob
import os
import sys


def rows(folder, pattern):
    path = glob.glob(os.path.join(folder, pattern))[0]
    return list(csv.DictReader(open(path)))


def q(values, p):
    return values[min(len(values) - 1, int(p * len(values)))] if values else float("nan")


for folder in sys.argv[1:]:
    link = rows(folder, "link_*_frames.csv")
    uart = rows(folder, "firmware_*_uart.csv")
    sent = [float(r["start_s"]) for r in link if r["from"] == "twin"]
    came = [float(r["start_s"]) for r in link if r["from"] != "twin"]
    written = [(float(r["end_s"]), float(r["baud"])) for r in uart if r["dir"] == "tx"]
    heard = [float(r["end_s"]) for r in uart if r["dir"] == "rx"]
    wait = sorted((s - (end + 20 / baud)) * 1e6 for s, (end, baud) in zip(sent, written))
    early = sorted(max(0.0, (c - h) * 1e6) for c, h in zip(came, heard))
    print("%s: %d replies waited after the sketch's line went quiet p50 %.0f, p90 %.0f, p99 %.0f us; "
          "requests reached the sketch early by p50 %.0f, p90 %.0f, p99 %.0f us"
          % (folder, len(wait), q(wait, .5), q(wait, .9), q(wait, .99),
             q(early, .5), q(early, .9), q(early, .99)))
