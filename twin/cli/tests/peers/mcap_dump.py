"""Everything the Python `mcap` package reads in an MCAP file, as JSON:
the header, the schemas and channels with their ids, every message (channel
id, sequence, log and publish time, data in hex) in file order, the metadata
and attachments, and the summary's statistics (null where there is none).

    python3 mcap_dump.py FILE
"""
import json
import sys

from mcap.reader import make_reader


def main(path):
    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        out["header"] = {"profile": header.profile, "library": header.library}
        summary = reader.get_summary()
        out["statistics"] = None
        if summary is not None and summary.statistics is not None:
            s = summary.statistics
            out["statistics"] = {
                "messages": s.message_count,
                "schemas": s.schema_count,
                "channels": s.channel_count,
                "metadata": s.metadata_count,
                "attachments": s.attachment_count,
                "per_channel": {str(k): v for k, v in sorted(s.channel_message_counts.items())},
            }
        f.seek(0)
        schemas, channels, messages = {}, {}, []
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            if schema is not None:
                schemas[str(schema.id)] = [schema.name, schema.encoding, schema.data.hex()]
            channels[str(channel.id)] = [
                channel.topic,
                channel.message_encoding,
                channel.schema_id,
                channel.metadata,
            ]
            messages.append(
                [channel.id, message.sequence, message.log_time, message.publish_time, message.data.hex()]
            )
        out["schemas"], out["channels"], out["messages"] = schemas, channels, messages
        f.seek(0)
        out["metadata"] = [[m.name, m.metadata] for m in make_reader(f).iter_metadata()]
        f.seek(0)
        out["attachments"] = [
            [a.name, a.media_type, a.log_time, a.create_time, a.data.hex()]
            for a in make_reader(f).iter_attachments()
        ]
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1])
