"""Reading a run log (eval.log.writer's MCAP files) by streaming its records, tolerating the
truncated tail of a killed run."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.records import Channel as ChannelRecord
from mcap.records import Header, Message, Metadata
from mcap.records import Schema as SchemaRecord
from mcap.stream_reader import StreamReader

MCAP_MAGIC = b"\x89MCAP0\r\n"  # the first and last 8 bytes of every MCAP file
# the length the writer gives the chunk it is still filling (set when the chunk is finished):
# a killed writer's file ends in one
UNFINISHED_RECORD_LENGTH = b"\xff" * 8


class LogReadError(ValueError):
    """The file is not a readable run log; the message says why and where."""


class TruncatedLogError(LogReadError):
    """The file ends before its footer: a killed run's log (readable with allow_truncated)."""



class _WholeReads:
    """A file whose short reads raise EndOfFile: a file cut inside a record (a killed
    writer) then reads as truncated rather than as garbage. `last` is the last read's data."""

    def __init__(self, f):
        self._f, self.last = f, b""

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        if n is not None and 0 < n != len(data):
            raise EndOfFile()
        self.last = data
        return data


@dataclass
class RunLog:
    """A log's messages: `messages[topic]` is a list of (log_time_ns, message), the
    message a dict on JSON channels, its encoded bytes on others (Foxglove's protobuf
    types); `schemas[topic]` the schema name; `metadata[name]` the metadata records;
    `truncated` True when the file ends early."""

    messages: dict = field(default_factory=dict)
    schemas: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    truncated: bool = False

    @property
    def start_ns(self) -> int:
        """The run's wall-clock start (ns since the epoch; 0 in logs whose log time is the
        simulation time alone): log time - start_ns = simulation time."""
        return int(self.metadata.get("time", {}).get("start_time_ns", 0))

    def count(self, topic: str) -> int:
        return len(self.messages.get(topic, ()))


def read_log(path, topics=None, allow_truncated: bool = False) -> RunLog:
    """Read the run log at `path` by streaming its records (no summary needed): JSON
    messages decoded, others (Foxglove's protobuf types) as their bytes.

    `topics`: decode only these (None: all). A file that ends before its footer (a killed
    run) raises LogReadError unless `allow_truncated`, when everything up to the last
    complete chunk is returned with `truncated` True. Anything else wrong (not an MCAP
    file, a bad CRC, undecodable JSON) raises LogReadError saying what and where.
    """
    path = Path(path)
    try:
        f = open(path, "rb")
    except OSError as exc:
        raise LogReadError(f"cannot open {path}: {exc.strerror or exc}") from None
    log = RunLog()
    channels, schemas, header = {}, {}, False  # channel id -> (topic, JSON?); schema id -> name
    with f:
        start = f.read(len(MCAP_MAGIC))
        if start != MCAP_MAGIC:
            what = "empty" if not start else f"it starts with {start!r}, not the MCAP magic"
            raise LogReadError(f"{path}: not an MCAP file ({what})")
        f.seek(0)
        try:
            stream = _WholeReads(f)
            for rec in StreamReader(stream, validate_crcs=True, record_size_limit=1 << 30).records:
                if isinstance(rec, Header):
                    header = True
                elif isinstance(rec, SchemaRecord):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, ChannelRecord):
                    channels[rec.id] = (rec.topic, rec.message_encoding == "json")
                    log.schemas[rec.topic] = schemas.get(rec.schema_id, "")
                elif isinstance(rec, Metadata):
                    log.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Message):
                    topic, is_json = channels.get(rec.channel_id, (None, False))
                    if topic is None:
                        raise LogReadError(f"{path}: message on unknown channel {rec.channel_id}")
                    if topics is not None and topic not in topics:
                        continue
                    try:
                        msg = json.loads(rec.data) if is_json else bytes(rec.data)
                    except (ValueError, UnicodeDecodeError) as exc:
                        raise LogReadError(f"{path}: undecodable JSON on {topic} at {rec.log_time} ns: {exc}") from None
                    log.messages.setdefault(topic, []).append((rec.log_time, msg))
        except (EndOfFile, RecordLengthLimitExceeded) as exc:
            if isinstance(exc, RecordLengthLimitExceeded) and stream.last != UNFINISHED_RECORD_LENGTH:
                raise LogReadError(f"{path}: corrupt MCAP file: {exc}") from None
            if not header:
                raise LogReadError(f"{path}: truncated before its MCAP header ({path.stat().st_size} bytes)") from None
            if not allow_truncated:
                raise TruncatedLogError(f"{path}: truncated: the file ends before its footer (a killed run?) "
                                        f"after {sum(map(len, log.messages.values()))} readable messages") from None
            log.truncated = True
        except LogReadError:
            raise
        except Exception as exc:  # bad magic, CRC, decompression, record parsing: all mean corrupt
            if not header:
                raise LogReadError(f"{path}: corrupt or truncated MCAP header: {exc}") from None
            raise LogReadError(f"{path}: corrupt MCAP file: {type(exc).__name__}: {exc}") from None
    return log
