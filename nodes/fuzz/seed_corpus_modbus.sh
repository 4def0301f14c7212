#!/usr/bin/env bash
# Writes the seed corpus of the Modbus fuzz targets:
#   corpus/modbus8_stream/  control byte (bit 0: CRC order) + frames of nodes/tests/vectors/modbus8.jsonl
#   corpus/rtu_stream/      control byte (bit 0: reply direction, bit 1: no timing) + RTU frames
#   corpus/tcp_stream/      MBAP frames
#   corpus/ascii_stream/    ASCII lines
# RTU/TCP/ASCII seeds cover every function code (01-06, 15, 16), request and
# reply, and an exception, built with the same CRC/LRC as the spec examples.
# The corpus is generated, not committed. Needs python3.
# Usage: nodes/fuzz/seed_corpus_modbus.sh   (CORPUS_DIR overrides the output,
# default nodes/fuzz/corpus)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
vectors=$here/../tests/vectors
corpus=${CORPUS_DIR:-$here/corpus}
python3 - "$vectors" "$corpus" <<'PY'
import json, pathlib, struct, sys

vectors, corpus = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])

def crc16(data):
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc

def write(target, name, data):
    d = corpus / target
    d.mkdir(parents=True, exist_ok=True)
    (d / name).write_bytes(data)

m8 = [json.loads(l) for l in open(vectors / "modbus8.jsonl") if l.strip()]
frames = [bytes.fromhex(v["frame_hex"]) for v in m8]
write("modbus8_stream", "all_high_first", b"\x00" + b"".join(frames))
write("modbus8_stream", "all_low_first", b"\x01" + b"".join(frames))
for i, f in enumerate(frames):
    write("modbus8_stream", f"frame_{i:02}", b"\x00" + f)
write("modbus8_stream", "stray_byte", b"\x00\x55" + frames[0] + frames[1])

requests = [
    bytes([1, 0, 0x13, 0, 37]), bytes([2, 0, 0xC4, 0, 22]), bytes([3, 0, 0x6B, 0, 3]),
    bytes([4, 0, 8, 0, 1]), bytes([5, 0, 0xAC, 0xFF, 0]), bytes([6, 0, 1, 0, 3]),
    bytes([15, 0, 0x13, 0, 10, 2, 0xCD, 0x01]), bytes([16, 0, 1, 0, 2, 4, 0, 10, 1, 2]),
    bytes([0x2B, 0x0E, 1, 0]),
]
replies = [
    bytes([1, 3, 0xCD, 0x6B, 0x05]), bytes([2, 3, 0xAC, 0xDB, 0x35]),
    bytes([3, 6, 2, 0x2B, 0, 0, 0, 0x64]), bytes([4, 2, 0, 10]), bytes([5, 0, 0xAC, 0xFF, 0]),
    bytes([6, 0, 1, 0, 3]), bytes([15, 0, 0x13, 0, 10]), bytes([16, 0, 1, 0, 2]),
    bytes([0x83, 0x02]),
]

def rtu(unit, pdu):
    body = bytes([unit]) + pdu
    return body + struct.pack("<H", crc16(body))

def tcp(tid, unit, pdu):
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu

def ascii_frame(unit, pdu):
    body = bytes([unit]) + pdu
    lrc = (-sum(body)) & 0xFF
    return b":" + (body + bytes([lrc])).hex().upper().encode() + b"\r\n"

for control in range(4):
    pdus = replies if control & 1 else requests
    write("rtu_stream", f"all_{control}", bytes([control]) + b"".join(rtu(1 + i, p) for i, p in enumerate(pdus)))
for i, p in enumerate(requests):
    write("rtu_stream", f"request_{i}", b"\x00" + rtu(1, p))
for i, p in enumerate(replies):
    write("rtu_stream", f"reply_{i}", b"\x01" + rtu(1, p))

write("tcp_stream", "requests", b"".join(tcp(i, 1, p) for i, p in enumerate(requests)))
write("tcp_stream", "replies", b"".join(tcp(i, 1, p) for i, p in enumerate(replies)))
write("tcp_stream", "resync", b"\xff\xff\xff" + tcp(9, 1, requests[5]))

write("ascii_stream", "requests", b"".join(ascii_frame(0xF7, p) for p in requests))
write("ascii_stream", "replies", b"noise" + b"".join(ascii_frame(1, p) for p in replies))
write("ascii_stream", "spec_example", b":F7031389000A60\r\n")
PY
for t in modbus8_stream rtu_stream tcp_stream ascii_stream; do echo "$t: $(ls "$corpus/$t" | wc -l) seeds"; done
