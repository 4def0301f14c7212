"""Writes an MCAP file as another program would, with the Python `mcap`
package's own writer: a profile and its library's name in the header, a
channel without a schema and two with one, channel metadata, sequence
numbers that skip, publish times apart from log times, metadata records
and an attachment between the chunks, small zstd chunks (many of them).

    python3 mcap_write.py FILE
"""
import json
import sys

from mcap.writer import CompressionType, Writer


def main(path):
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=4096, compression=CompressionType.ZSTD)
        w.start(profile="x-lab", library="a lab's logger 3.1")
        point = w.register_schema(
            name="lab.Point",
            encoding="jsonschema",
            data=json.dumps({"type": "object"}).encode(),
        )
        note = w.register_schema(name="lab.Note", encoding="jsonschema", data=b"{}")
        channels = [
            w.register_channel("/raw", "json", 0),
            w.register_channel("/point", "json", point, {"frame": "bench", "rate_hz": "100"}),
            w.register_channel("/note", "json", note),
        ]
        w.add_metadata("run", {"operator": "lab", "seed": "7"})
        for i in range(3000):
            channel = channels[i % 7 % 3]
            t = 1_000_000_000 + i * 1_000_000
            data = json.dumps({"i": i, "x": i * 0.37}).encode()
            w.add_message(channel, log_time=t, data=data, publish_time=t - 250, sequence=3 * i + 1)
            if i == 1200:
                w.add_attachment(
                    create_time=5, log_time=t, name="fw.hex", media_type="text/plain",
                    data=b":00000001FF\n" * 40,
                )
            if i == 2000:
                w.add_metadata("checkpoint", {"at": str(i)})
        w.finish()


if __name__ == "__main__":
    main(sys.argv[1])
