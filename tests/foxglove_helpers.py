"""Read back what phim writes for Foxglove: MCAP messages of protobuf channels -> plain dicts.

No protobuf runtime is installed, so this decodes the protobuf wire format itself, guided by the schema the
MCAP file carries (a FileDescriptorSet per channel): field names and types come from the file, nothing is
hard-coded. Enough for foxglove's schemas (scalars, strings, bytes, nested and repeated messages, packed
repeated numbers); unset proto3 fields are absent from the dicts.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

# FieldDescriptorProto.Type -> struct format of fixed-width values (varints are decoded apart)
FIXED = {1: "<d", 2: "<f", 6: "<Q", 7: "<I", 15: "<i", 16: "<q"}
MESSAGE, BYTES, STRING, BOOL = 11, 12, 9, 8
SIGNED = {3: 64, 5: 32}  # int64, int32: two's complement in 64-bit varints


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        b = buf[i]
        value |= (b & 0x7F) << shift
        i += 1
        if b < 0x80:
            return value, i
        shift += 7


def _raw_fields(buf: bytes) -> Iterator[tuple[int, int, Any]]:
    """(field number, wire type, int or bytes) of every field of one message."""
    i = 0
    sizes = {1: 8, 5: 4}
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire == 2:
            n, i = _varint(buf, i)
            value, i = buf[i : i + n], i + n
        elif wire in sizes:
            value, i = buf[i : i + sizes[wire]], i + sizes[wire]
        else:
            raise ValueError(f"wire type {wire} not supported")
        yield number, wire, value


def descriptors(schema_data: bytes) -> dict[str, dict[int, tuple[str, int, str, bool]]]:
    """A FileDescriptorSet -> {".pkg.Message": {field number: (name, type, type_name, repeated)}}."""
    out: dict[str, dict[int, tuple[str, int, str, bool]]] = {}

    def message(buf: bytes, scope: str) -> None:
        parts = list(_raw_fields(buf))
        name = scope + "." + next(v.decode() for n, _, v in parts if n == 1)
        fields = {}
        for n, _, v in parts:
            if n == 2:  # FieldDescriptorProto: name 1, number 3, label 4, type 5, type_name 6
                f = {k: val for k, _, val in _raw_fields(v)}
                fields[f[3]] = (f[1].decode(), f[5], f.get(6, b"").decode(), f.get(4) == 3)
            elif n == 3:  # nested message types
                message(v, name)
        out[name] = fields

    for n, _, file_buf in _raw_fields(schema_data):
        if n != 1:
            continue
        parts = list(_raw_fields(file_buf))
        package = next((v.decode() for k, _, v in parts if k == 2), "")
        for k, _, v in parts:
            if k == 4:
                message(v, "." + package if package else "")
    return out


def _scalar(kind: int, wire: int, value: Any) -> Any:
    if kind in FIXED:
        return struct.unpack(FIXED[kind], value)[0]
    if kind == STRING:
        return value.decode()
    if kind == BOOL:
        return bool(value)
    if kind in SIGNED and value >= 1 << (SIGNED[kind] - 1):
        return value - (1 << 64)
    return value


def decode(types: dict, name: str, buf: bytes) -> dict[str, Any]:
    """One protobuf message of type `name` (".foxglove.SceneUpdate") -> {field name: value}."""
    fields, out = types[name], {}
    for number, wire, value in _raw_fields(buf):
        if number not in fields:
            continue
        fname, kind, type_name, repeated = fields[number]
        if kind == MESSAGE:
            items = [decode(types, type_name, value)]
        elif kind == BYTES:
            items = [bytes(value)]
        elif wire == 2 and kind != STRING:  # packed repeated numbers
            items = _packed(kind, value)
        else:
            items = [_scalar(kind, wire, value)]
        if repeated:
            out.setdefault(fname, []).extend(items)
        else:
            out[fname] = items[0]
    return out


def _packed(kind: int, buf: bytes) -> list[Any]:
    if kind in FIXED:
        size = struct.calcsize(FIXED[kind])
        return [struct.unpack(FIXED[kind], buf[i : i + size])[0] for i in range(0, len(buf), size)]
    values, i = [], 0
    while i < len(buf):
        v, i = _varint(buf, i)
        values.append(_scalar(kind, 0, v))
    return values


def read_foxglove_mcap(path: Path) -> list[tuple[str, int, dict[str, Any]]]:
    """Every message of an MCAP file's protobuf channels -> (topic, log_time, decoded dict), in log order."""
    from mcap.reader import make_reader

    out = []
    with open(path, "rb") as f:
        reader = make_reader(f)
        cache: dict[int, dict] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert channel.message_encoding == "protobuf" and schema is not None, channel
            if schema.id not in cache:
                cache[schema.id] = descriptors(schema.data)
            out.append(
                (channel.topic, message.log_time, decode(cache[schema.id], "." + schema.name, message.data))
            )
    return out
