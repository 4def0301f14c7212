"""Reads an MCAP file as a user of the Python `mcap` package would, with its
`make_reader` on the file (the seeking reader: summary first, else the file
read through) and on a pipe-like stream (the non-seeking reader), each with
its default arguments.

    python3 mcap_read.py FILE

Prints one JSON object: whether the footer names a summary, the summary's
message count, the messages each reader iterated (or the error that stopped
it, with how many it had yielded), and the metadata records' names.
"""
import io
import json
import sys

from mcap.reader import make_reader


class Pipe(io.RawIOBase):
    """The file's bytes as a stream that cannot seek (a pipe, a socket)."""

    def __init__(self, data):
        self._data = io.BytesIO(data)

    def readable(self):
        return True

    def seekable(self):
        return False

    def readinto(self, buffer):
        chunk = self._data.read(len(buffer))
        buffer[: len(chunk)] = chunk
        return len(chunk)


def iterate(stream):
    reader = make_reader(stream)
    n = 0
    try:
        for _ in reader.iter_messages():
            n += 1
    except Exception as e:  # what stopped it is the finding
        return {"messages": n, "error": f"{type(e).__name__}: {e}"}
    return {"messages": n, "error": None}


def main(path):
    out = {}
    with open(path, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
            out["summary"] = summary is not None
            out["summary_messages"] = (
                summary.statistics.message_count
                if summary is not None and summary.statistics is not None
                else None
            )
        except Exception as e:
            out["summary"] = f"{type(e).__name__}: {e}"
            out["summary_messages"] = None
        f.seek(0)
        out["seeking"] = iterate(f)
        f.seek(0)
        try:
            out["metadata"] = [m.name for m in make_reader(f).iter_metadata()]
        except Exception as e:
            out["metadata"] = f"{type(e).__name__}: {e}"
        f.seek(0)
        out["streaming"] = iterate(io.BufferedReader(Pipe(f.read())))
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1])
