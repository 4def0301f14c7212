"""Reads a `twin check` recording as a user of the Python `mcap` package
would (`mcap` and `mcap-protobuf-support`, tools we did not write): the
frames of the link channel decoded from their protobuf, the checks'
messages, the metadata and the attachments' names.

    python3 check_recording.py FILE

Prints one JSON object: `run` and `check` (the `twin.run` and `twin.check`
metadata), `attachments` (names), `frames` (`topic`, `from`, `time_s` the
log time, `text` the bytes as text, `protocol` and `cmd` as decoded) and
`checks` (each check's message as recorded), in the order read.
"""
import json
import sys

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


def main(path):
    out = {"run": None, "check": None, "attachments": [], "frames": [], "checks": []}
    with open(path, "rb") as f:
        reader = make_reader(f)
        protobuf = DecoderFactory()
        for record in reader.iter_metadata():
            if record.name == "twin.run":
                out["run"] = dict(record.metadata)
            elif record.name == "twin.check":
                out["check"] = dict(record.metadata)
        out["attachments"] = [a.name for a in reader.iter_attachments()]
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.message_encoding == "json":
                decoded = json.loads(message.data)
            else:
                decoded = protobuf.decoder_for(channel.message_encoding, schema)(message.data)
            if channel.topic.startswith("/link/"):
                out["frames"].append(
                    {
                        "topic": channel.topic,
                        "from": decoded.__getattribute__("from"),
                        "time_s": message.log_time / 1e9,
                        # Printable frames are stored as text; the others as hex.
                        "text": decoded.text or bytes.fromhex(decoded.hex).decode("latin-1"),
                        "protocol": decoded.decoded.protocol,
                        "cmd": decoded.decoded.cmd,
                    }
                )
            elif channel.topic == "/check/checks":
                out["checks"].append(decoded)
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1])
