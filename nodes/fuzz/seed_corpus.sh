#!/usr/bin/env bash
# Writes the seed corpus of every fuzz target from the test vectors (nodes/tests/vectors):
#   corpus/meb_parse/      one file per frame of meb.jsonl and meb_slave.jsonl
#   corpus/meb_stream/     those frames concatenated, in vector order and by request/reply pair
#   corpus/pwmcap_decode/  captured widths of a few frames in the paper's and Table 2's codings
# The corpus is generated, not committed (fuzz/.gitignore), from the vectors and from
# found/, what earlier campaigns found. Needs python3.
# Usage: nodes/fuzz/seed_corpus.sh
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
vectors=$here/../tests/vectors
python3 - "$vectors" "$here/corpus" <<'PY'
import json, pathlib, struct, sys

vectors, corpus = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
frames = [json.loads(l)["frame"] for l in open(vectors / "meb.jsonl") if l.strip()]
pairs = [json.loads(l) for l in open(vectors / "meb_slave.jsonl") if l.strip()]
slave = [p["request"] for p in pairs] + [p["reply"] for p in pairs if p.get("reply")]

def write(target, name, data):
    d = corpus / target
    d.mkdir(parents=True, exist_ok=True)
    (d / name).write_bytes(data)

for i, f in enumerate(frames + slave):
    write("meb_parse", f"frame_{i:03}", f.encode())
write("meb_stream", "vectors", "".join(frames).encode())
write("meb_stream", "slave_pairs", "".join(p["request"] + (p.get("reply") or "") for p in pairs).encode())
write("meb_stream", "resync", b"@01EA@01EA000346*\n")

# Coding (data bits, dummy bits, start ticks), kind (0 broadcast, 1 designated,
# 2 experiment) and symbol values after the start, as PwmFrame::emit writes them.
frames_pwm = [
    ((8, 2, 200), 0, [0x10, 10, 128, 255]),
    ((8, 2, 200), 1, [0x32, 1000 >> 2]),
    ((8, 2, 200), 2, [0x04, 0x12, 100, 255]),
    ((8, 0, 100), 2, [0x03, 0x03, 0, 7]),
    ((12, 4, 500), 0, [0x01] + list(range(0, 4096, 300))),
]
for i, ((bits, dummy, start), kind, values) in enumerate(frames_pwm):
    widths = [start] + [start + (v << dummy) for v in values]
    data = bytes([bits, dummy]) + struct.pack("<HB", start, kind) + b"".join(struct.pack("<I", w) for w in widths)
    write("pwmcap_decode", f"frame_{i}", data)
PY
# What earlier fuzzing campaigns found (campaign.sh, minimised with `cargo
# fuzz cmin`), kept in git so every run starts from there.
for found in "$here"/found/*/; do
  [ -d "$found" ] || continue
  target=$(basename "$found")
  mkdir -p "$here/corpus/$target"
  cp -n "$found"* "$here/corpus/$target/"
done
for t in "$here"/corpus/*/; do echo "$(basename "$t"): $(ls "$t" | wc -l) seeds"; done
