"""ROS 2 message classes for Cyclone DDS, derived from the ``rosbags`` Jazzy type store.

One source of definitions: the field lists come from ``rosbags``' ROS 2 Jazzy store (the
same store the bag code uses), and each message becomes a ``cyclonedds`` ``IdlStruct``
with ROS 2's DDS type name ``pkg::msg::dds_::Type_``. Samples are serialized as plain
XCDR1, the encoding rmw_cyclonedds_cpp uses, byte for byte what ``rosbags`` writes.

Numeric arrays (``uint8[] data`` of an Image, ``float64[] data`` of a
Float64MultiArray, ...) are serialized from and deserialized to numpy arrays in one block
copy instead of Python's element-by-element path (about 100x faster for an image).
"""
from __future__ import annotations

import dataclasses
import struct
import threading
from functools import lru_cache
from typing import Any

import numpy as np
from cyclonedds.idl import IdlMeta, IdlStruct, types
from cyclonedds.idl._machinery import Machine, PrimitiveMachine, SequenceMachine, StructMachine
from cyclonedds.idl._support import Endianness
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore

from hdrqn_ros.middleware.arrays import as_array

_IDL = {"bool": types.uint8, "byte": types.uint8, "char": types.uint8, "octet": types.uint8,
        "int8": types.int8, "uint8": types.uint8, "int16": types.int16, "uint16": types.uint16,
        "int32": types.int32, "uint32": types.uint32, "int64": types.int64, "uint64": types.uint64,
        "float32": types.float32, "float64": types.float64, "string": str}
_DTYPE = {"bool": np.uint8, "byte": np.uint8, "char": np.uint8, "octet": np.uint8, "int8": np.int8,
          "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
          "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64}
_lock = threading.Lock()


@lru_cache(maxsize=1)
def typestore():
    """The ``rosbags`` ROS 2 Jazzy type store (message definitions, CDR reference codec)."""
    return get_typestore(Stores.ROS2_JAZZY)


def dds_type_name(type_name: str) -> str:
    """``"sensor_msgs/msg/Image"`` -> ``"sensor_msgs::msg::dds_::Image_"``."""
    pkg, kind, name = _split(type_name)
    return f"{pkg}::{kind}::dds_::{name}_"


def _split(type_name: str) -> tuple[str, str, str]:
    parts = type_name.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"message type must look like 'pkg/msg/Type', got {type_name!r}")
    return parts[0], parts[1], parts[2]


class DecodeError(ValueError):
    """CDR bytes that are not a sample of the expected message type (truncated, garbled)."""


_DECODE_FAILURES = (struct.error, ValueError)
"""What cyclonedds' deserializer raises on bytes that do not fit the type: a read past the
end (struct.error), bad UTF-8 in a string, a sequence longer than the sample (ValueError);
``test/test_fuzz.py`` feeds it random and mutated samples."""


def decode(cls: type, data: bytes) -> Any:
    """The message of class ``cls`` (from :func:`message_class`) in the CDR ``data``,
    encapsulation header first; :class:`DecodeError` naming the type if they do not decode."""
    if len(data) < 4:
        raise DecodeError(f"{len(data)} B is not a {cls.__ros_type__} sample (shorter than the 4-byte CDR header)")
    try:
        return cls.deserialize(bytes(data), has_header=True)
    except _DECODE_FAILURES as exc:
        raise DecodeError(f"bytes do not decode as {cls.__ros_type__} ({type(exc).__name__}: {exc})") from None


def message_class(type_name: str) -> type:
    """The ``IdlStruct`` class for ``type_name``; built once, then cached."""
    with _lock:
        return _build(type_name)


@lru_cache(maxsize=None)
def _build(type_name: str) -> type:
    store = typestore()
    if type_name not in store.fielddefs:
        raise ValueError(f"unknown message type {type_name!r} (not in the ROS 2 Jazzy type store)")
    _, fields = store.fielddefs[type_name]
    _, _, name = _split(type_name)
    ns = IdlMeta.__prepare__(name, (IdlStruct,), typename=dds_type_name(type_name))
    fast: dict[str, np.dtype] = {}
    for fname, desc in fields:
        idl_type, default = _field(desc)
        ns["__annotations__"][fname] = idl_type
        ns[fname] = dataclasses.field(default_factory=default)
        base = _numeric_sequence(desc)
        if base is not None:
            fast[fname] = np.dtype(_DTYPE[base])
    cls = dataclasses.dataclass(IdlMeta(name, (IdlStruct,), ns))
    cls.__ros_type__ = type_name
    if fast:
        _install_fast_sequences(cls, fast)
    return cls


def _field(desc) -> tuple[Any, Any]:
    """(IDL annotation, default factory) for a rosbags field descriptor."""
    kind, rest = desc
    if kind == Nodetype.BASE:
        base = rest[0]
        if base == "string":
            return str, str
        if base.startswith("float"):
            return _IDL[base], float
        return _IDL[base], int
    if kind == Nodetype.NAME:
        cls = _build(rest)
        return cls, cls
    sub, size = rest
    sub_type, sub_default = _field(sub)
    if kind == Nodetype.ARRAY:
        return types.array[sub_type, size], lambda: [sub_default() for _ in range(size)]
    if _numeric_sequence(desc) is not None:
        dtype = _DTYPE[sub[1][0]]
        return types.sequence[sub_type], lambda: np.zeros(0, dtype)
    return types.sequence[sub_type], list


def _numeric_sequence(desc) -> str | None:
    kind, rest = desc
    if kind != Nodetype.SEQUENCE:
        return None
    (sub_kind, sub_rest), _ = rest
    if sub_kind == Nodetype.BASE and sub_rest[0] in _DTYPE:
        return sub_rest[0]
    return None


class _NumpySequenceMachine(Machine):
    """CDR ``sequence<primitive>`` <-> 1-D numpy array as one block copy (same bytes as
    the element-wise machine: uint32 length, alignment to the element size, elements)."""

    def __init__(self, dtype: np.dtype):
        self.dtype = dtype
        self.alignment = 4

    def serialize(self, buffer, value, *args, **kwargs):
        data = np.ascontiguousarray(value, dtype=self.dtype).reshape(-1)
        buffer.align(4)
        buffer.write("I", 4, data.size)
        if data.size:
            buffer.align(self.dtype.itemsize)
            if buffer.endianness != Endianness.native():
                data = data.byteswap()
            buffer.write_bytes(data.tobytes())

    def deserialize(self, buffer, *args, **kwargs):
        buffer.align(4)
        n = buffer.read("I", 4)
        if not n:
            return np.zeros(0, self.dtype)
        buffer.align(self.dtype.itemsize)
        dtype = self.dtype.newbyteorder("<" if buffer.endianness == Endianness.Little else ">")
        raw = buffer.read_bytes(n * self.dtype.itemsize)
        if len(raw) != n * self.dtype.itemsize:  # the sample ends before the elements it announces
            raise DecodeError(f"a sequence of {n} {self.dtype} values runs past the end of the sample "
                              f"({len(raw)} bytes left)")
        return np.frombuffer(raw, dtype).astype(self.dtype, copy=False)

    def key_scan(self):
        return SequenceMachine(PrimitiveMachine(types.uint8)).key_scan()

    def cdr_key_machine_op(self, skip):
        return []

    def default_initialize(self):
        return np.zeros(0, self.dtype)


def _install_fast_sequences(cls: type, fields: dict[str, np.dtype]) -> None:
    """Swap the element-wise sequence machines of ``fields`` for numpy block copies."""
    idl = cls.__idl__
    idl.populate()
    for machine in (idl.v1_machine, idl.v2_machine):
        if isinstance(machine, StructMachine):
            for fname, dtype in fields.items():
                machine.members_machines[fname] = _NumpySequenceMachine(dtype)


def to_rosbags(msg: Any, type_name: str | None = None) -> Any:
    """The ``rosbags`` twin of a Cyclone message (for CDR comparisons and bag writing)."""
    type_name = type_name or msg.__ros_type__
    store = typestore()
    _, fields = store.fielddefs[type_name]
    values = {}
    for fname, desc in fields:
        values[fname] = _value_to_rosbags(getattr(msg, fname), desc, store)
    return store.types[type_name](**values)


def _value_to_rosbags(value, desc, store):
    kind, rest = desc
    if kind == Nodetype.BASE:
        return bool(value) if rest[0] == "bool" else value
    if kind == Nodetype.NAME:
        return to_rosbags(value, rest)
    sub, _ = rest
    base = _numeric_sequence(desc) or (sub[1][0] if sub[0] == Nodetype.BASE and sub[1][0] in _DTYPE else None)
    if base is not None:
        return as_array(value, _DTYPE[base])
    return [_value_to_rosbags(v, sub, store) for v in value]
