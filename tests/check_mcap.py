#!/usr/bin/env python3
"""Validate an sdsem run record (MCAP) with the reference Python reader.

Usage:
    python3 tests/check_mcap.py RUN.mcap [--require-all-topics]

Needs only the `mcap` package (pip install mcap). Protobuf messages are decoded against
the FileDescriptorSet stored in each channel's schema by a small wire-format decoder
below, so `protobuf` is not needed; JSON messages must parse and carry the fields their
JSON schema marks as required.

Checks (DESIGN §5):
  * every record reads linearly, as a killed run leaves them: a record cut short is read up to
    its last whole chunk and reported INCOMPLETE (a problem only with --require-all-topics);
  * a finished file also reads with mcap's summary-based reader, message for message;
  * every topic is one of the contract topics (or of the Foxglove views beyond them: the
    frames on /tf, the height preview and its legend, the mesh), with its schema and encodings;
  * every protobuf message decodes against its schema, and RawImage / PointCloud / Log
    messages are self-consistent (data size = width x height x bytes per pixel, ...);
  * every JSON message parses and has its schema's required keys;
  * with --require-all-topics, all eight topics are present.

Exit status 0 when everything holds, 1 otherwise (each problem printed on stderr).
To produce a sample file from the Rust side:
    SDSEM_MCAP_SAMPLE=/tmp/sample.mcap cargo test -p sdsem --lib record::tests::write_sample -- --ignored
"""

import json
import struct
import sys

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

CONTRACT = {
    "/sem/frame": ({"foxglove.RawImage", "foxglove.CompressedImage"}, "protobuf"),
    "/sem/frame_info": ({"sdsem.FrameInfo"}, "json"),
    "/stage/state": ({"sdsem.StageState"}, "json"),
    "/stage/io": ({"sdsem.StageIo"}, "json"),
    "/recon/height": ({"foxglove.RawImage"}, "protobuf"),
    "/recon/pointcloud": ({"foxglove.PointCloud"}, "protobuf"),
    "/recon/report": ({"sdsem.ReconReport"}, "json"),
    "/log": ({"foxglove.Log"}, "protobuf"),
}

# Beyond DESIGN §5: what a reconstruction adds so Foxglove shows it right (src/record/reconstruction.rs).
VIEWS = {
    "/tf": ({"foxglove.FrameTransforms"}, "protobuf"),
    "/recon/height_preview": ({"foxglove.CompressedImage"}, "protobuf"),
    "/recon/height_preview/legend": ({"foxglove.ImageAnnotations"}, "protobuf"),
    "/recon/mesh": ({"foxglove.SceneUpdate"}, "protobuf"),
}

# --- minimal protobuf wire-format decoding -------------------------------------------


def read_varint(buf, pos):
    result = shift = 0
    while True:
        if pos >= len(buf):
            raise ValueError("truncated varint")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7
        if shift > 63:
            raise ValueError("varint too long")


def fields(buf):
    """Yield (field number, wire type, value) of a serialized message."""
    pos = 0
    while pos < len(buf):
        key, pos = read_varint(buf, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = read_varint(buf, pos)
        elif wire == 1:
            value, pos = buf[pos:pos + 8], pos + 8
        elif wire == 2:
            length, pos = read_varint(buf, pos)
            value, pos = buf[pos:pos + length], pos + length
        elif wire == 5:
            value, pos = buf[pos:pos + 4], pos + 4
        else:
            raise ValueError(f"unsupported wire type {wire}")
        if pos > len(buf):
            raise ValueError("truncated field")
        yield number, wire, value


def parse_descriptor_set(data):
    """Map full message name -> {field number: (name, type, type_name, repeated)}."""
    messages = {}

    def message(buf, scope):
        name, fields_, nested = None, {}, []
        for number, _, value in fields(buf):
            if number == 1:
                name = value.decode()
            elif number == 2:
                f = {1: None, 3: None, 4: 1, 5: None, 6: ""}
                for n, _, v in fields(value):
                    f[n] = v.decode() if n in (1, 6) else v
                fields_[f[3]] = (f[1], f[5], f[6], f[4] == 3)
            elif number == 3:
                nested.append(value)
        full = f"{scope}.{name}" if scope else name
        messages[full] = fields_
        for n in nested:
            message(n, full)

    for number, _, file_bytes in fields(data):
        if number != 1:
            continue
        package, types = "", []
        for n, _, v in fields(file_bytes):
            if n == 2:
                package = v.decode()
            elif n == 4:
                types.append(v)
        for t in types:
            message(t, package)
    return messages


def decode(messages, full_name, buf):
    """Decode `buf` as message `full_name`; unknown fields are an error."""
    spec = messages.get(full_name)
    if spec is None:
        raise ValueError(f"message type {full_name} not in the schema's descriptors")
    out = {}
    for number, wire, value in fields(buf):
        if number not in spec:
            raise ValueError(f"{full_name}: unknown field {number}")
        name, ftype, type_name, repeated = spec[number]
        if ftype == 11:
            v = decode(messages, type_name.lstrip("."), value)
        elif ftype == 9:
            v = value.decode()
        elif ftype == 12:
            v = bytes(value)
        elif ftype == 7:
            v = struct.unpack("<I", value)[0]
        elif ftype == 2:
            v = struct.unpack("<f", value)[0]
        elif ftype == 1:
            v = struct.unpack("<d", value)[0]
        elif ftype in (3, 4, 5, 8, 13, 14):
            v = value
        else:
            v = value
        if repeated:
            out.setdefault(name, []).append(v)
        else:
            out[name] = v
    return out


# --- checks ------------------------------------------------------------------------------

BYTES_PER_PIXEL = {"mono8": 1, "8UC1": 1, "mono16": 2, "16UC1": 2, "32FC1": 4}


def check_protobuf(topic, schema_name, msg, problems):
    if schema_name == "foxglove.RawImage":
        bpp = BYTES_PER_PIXEL.get(msg.get("encoding"))
        if bpp is None:
            problems.append(f"{topic}: unexpected image encoding {msg.get('encoding')!r}")
            return
        w, h, step = msg.get("width", 0), msg.get("height", 0), msg.get("step", 0)
        if step < w * bpp or len(msg.get("data", b"")) != step * h:
            problems.append(f"{topic}: {w}x{h} {msg['encoding']} image with step {step} "
                            f"holds {len(msg.get('data', b''))} bytes")
        if topic == "/sem/frame" and msg.get("frame_id") not in ("tracking", "left", "right"):
            problems.append(f"{topic}: frame_id {msg.get('frame_id')!r}")
        if topic == "/recon/height" and msg.get("encoding") != "32FC1":
            problems.append(f"{topic}: height map must be 32FC1")
    elif schema_name == "foxglove.PointCloud":
        names = [f.get("name") for f in msg.get("fields", [])]
        stride = msg.get("point_stride", 0)
        if names[:3] != ["x", "y", "z"] or stride == 0 or len(msg.get("data", b"")) % stride:
            problems.append(f"{topic}: point cloud fields {names}, stride {stride}")
    elif schema_name == "foxglove.Log":
        if msg.get("level", 0) not in range(1, 6) or "message" not in msg:
            problems.append(f"{topic}: log level {msg.get('level')} / no message")
    elif schema_name == "foxglove.CompressedImage":
        data = msg.get("data", b"")
        if msg.get("format") == "png" and not data.startswith(b"\x89PNG\r\n\x1a\n"):
            problems.append(f"{topic}: format png, but the data is not a PNG file")
    elif schema_name == "foxglove.FrameTransforms":
        for t in msg.get("transforms", []):
            if not t.get("parent_frame_id") or not t.get("child_frame_id"):
                problems.append(f"{topic}: a transform without parent or child frame")
    elif schema_name == "foxglove.SceneUpdate":
        for entity in msg.get("entities", []):
            for model in entity.get("models", []):
                data = model.get("data", b"")
                if model.get("media_type") != "model/gltf-binary" or data[:4] != b"glTF" \
                        or struct.unpack("<I", data[8:12])[0] != len(data):
                    problems.append(f"{topic}: entity {entity.get('id')!r}: model is not a whole GLB")


def check_message(schema, channel, message, state, problems):
    """Checks one message against its topic's schema (DESIGN §5 or VIEWS)."""
    topic = channel.topic
    state["counts"][topic] = state["counts"].get(topic, 0) + 1
    expected = CONTRACT.get(topic) or VIEWS.get(topic)
    if expected is None:
        problems.append(f"{topic}: not a contract topic")
        return
    names, encoding = expected
    if schema is None or schema.name not in names or channel.message_encoding != encoding:
        problems.append(f"{topic}: schema {schema and schema.name}, "
                        f"encoding {channel.message_encoding}")
        return
    try:
        if encoding == "protobuf":
            if schema.encoding != "protobuf":
                raise ValueError(f"schema encoding {schema.encoding}")
            if schema.id not in state["descriptors"]:
                state["descriptors"][schema.id] = parse_descriptor_set(schema.data)
            msg = decode(state["descriptors"][schema.id], schema.name, message.data)
            check_protobuf(topic, schema.name, msg, problems)
        else:
            if schema.encoding != "jsonschema":
                raise ValueError(f"schema encoding {schema.encoding}")
            if schema.id not in state["required"]:
                js = json.loads(schema.data)
                if js.get("type") != "object":
                    raise ValueError("JSON schema is not an object schema")
                state["required"][schema.id] = js.get("required", [])
            value = json.loads(message.data)
            missing = [k for k in state["required"][schema.id] if k not in value]
            if missing:
                raise ValueError(f"missing required keys {missing}")
    except (ValueError, UnicodeDecodeError, struct.error) as e:
        problems.append(f"{topic}: message at {message.log_time} does not decode: {e}")


def read_linearly(f, state, problems):
    """Reads every record from the start, as a killed run leaves them: stops quietly at the
    first cut or damaged record. Returns (complete, where it stopped)."""
    schemas, channels = {}, {}
    try:
        for record in StreamReader(f, validate_crcs=True).records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None:
                    problems.append(f"message on unknown channel {record.channel_id}")
                    continue
                check_message(schemas.get(channel.schema_id), channel, record, state, problems)
            elif isinstance(record, Metadata):
                state["metadata"].append(record.name)
            elif isinstance(record, Attachment):
                state["attachments"].append(record.name)
            elif isinstance(record, Footer):
                return True, None
    except (McapError, EOFError, ValueError, struct.error, OSError) as e:
        return False, f"{type(e).__name__} after byte {f.tell()}: {e}"
    return False, "the file ends without a footer"


def main(argv):
    args = [a for a in argv[1:] if not a.startswith("--")]
    require_all = "--require-all-topics" in argv
    if len(args) != 1:
        print(__doc__, file=sys.stderr)
        return 2
    problems = []
    state = {"counts": {}, "descriptors": {}, "required": {}, "metadata": [], "attachments": []}
    with open(args[0], "rb") as f:
        complete, stopped = read_linearly(f, state, problems)
        if complete:
            # A finished record also reads through its summary, message for message.
            f.seek(0)
            reader = make_reader(f)
            if reader.get_summary() is None:
                problems.append("no summary section")
            elif sum(1 for _ in reader.iter_messages()) != sum(state["counts"].values()):
                problems.append("the summary-based reader sees other messages than a linear read")
        else:
            print(f"INCOMPLETE: {stopped}; everything before it was read")
            if require_all:
                problems.append("the record is incomplete (a killed run?)")
    if require_all:
        for topic in CONTRACT:
            if topic not in state["counts"]:
                problems.append(f"{topic}: missing")
    for topic in sorted(state["counts"]):
        print(f"{topic:30s} {state['counts'][topic]:6d} messages")
    print(f"metadata: {', '.join(state['metadata']) or '-'}")
    print(f"attachments: {', '.join(state['attachments']) or '-'}")
    for p in problems:
        print(f"PROBLEM: {p}", file=sys.stderr)
    print("OK" if not problems else f"{len(problems)} problem(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
