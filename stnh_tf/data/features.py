"""The TFRecord feature spec: the one module that both the writer and every parser import.

Each record is a ``tf.train.Example`` with these features (``S = 128``, ``C = 192``):

===============  =====================  =======================================================
name             stored as              meaning
===============  =====================  =======================================================
``patch_a``      bytes, uint8 [S, S]    patch of image_a at the square (stage k: re-cropped
                                        ``patch_a_k``)
``patch_b``      bytes, uint8 [S, S]    patch of image_b at the same square
``patch_a_t``    bytes, uint8 [S, S]    ``patch_a`` warped with the true ``h_ba`` (zero outside):
                                        ``patch_a_t(p) = patch_a(h_ba @ p)``
``context_a``    bytes, uint8 [C, C]    ``image_a[y0-32 : y0+160, x0-32 : x0+160]``
``h_bar``        float32 [8]            this stage's normalized target: first eight entries of
                                        ``M @ H_target @ inv(M)`` with ``[2, 2] = 1``
``h_ba``         float32 [9]            true pixel ``H_ba`` of the original pair, patch frame,
                                        patch_b -> patch_a, row-major, ``[2, 2] = 1``
``h_prev``       float32 [9]            composed earlier-stage estimate (patch pixel frame);
                                        identity for stage 1
``h_mask``       float32 []             1.0 = ground truth present
``square_xy``    int64 [2]              ``(x0, y0)`` of the square in the 320x240 image_a
``image_id``     bytes []               source image id (UTF-8)
``index``        int64 []               global sample index
===============  =====================  =======================================================

The serializer writes the protobuf wire format directly (deterministic: features sorted by name,
packed numeric lists), so writer processes need neither TensorFlow nor the TF protobuf classes;
the bytes parse with ``tf.train.Example.FromString`` and ``tf.io.parse_example``.
:func:`decode_example` reads them back with NumPy only; :func:`parse_examples` is the TensorFlow
parser (TensorFlow is imported only when it is called).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from stnh_tf import geometry

S = geometry.PATCH_SIZE
CONTEXT_SIZE = geometry.PATCH_SIZE + 2 * geometry.MAX_PERTURBATION


@dataclasses.dataclass(frozen=True)
class Field:
    """One feature. ``kind``: "raw" (uint8 array as one bytes value), "float", "int64", "string"."""

    name: str
    kind: str
    shape: tuple

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def numpy_dtype(self):
        kinds = {"raw": np.uint8, "float": np.float32, "int64": np.int64, "string": object}
        return kinds[self.kind]


FIELDS = (
    Field("patch_a", "raw", (S, S)),
    Field("patch_b", "raw", (S, S)),
    Field("patch_a_t", "raw", (S, S)),
    Field("context_a", "raw", (CONTEXT_SIZE, CONTEXT_SIZE)),
    Field("h_bar", "float", (8,)),
    Field("h_ba", "float", (9,)),
    Field("h_prev", "float", (9,)),
    Field("h_mask", "float", ()),
    Field("square_xy", "int64", (2,)),
    Field("image_id", "string", ()),
    Field("index", "int64", ()),
)
FIELD_BY_NAME = {f.name: f for f in FIELDS}
FEATURE_NAMES = tuple(f.name for f in FIELDS)
FORMAT_VERSION = "stnh-tf-pairs/1"


def spec_as_dict() -> dict:
    """The spec as JSON-ready data (recorded in ``metadata.json``)."""
    return {"format": FORMAT_VERSION,
            "fields": {f.name: {"kind": f.kind, "shape": list(f.shape)} for f in FIELDS}}


# ------------------------------------------------------------------------------------------------
# Protobuf wire format (tf.train.Example), written and read without TensorFlow
# ------------------------------------------------------------------------------------------------
def _varint(n: int) -> bytes:
    if n < 0:
        n += 1 << 64
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _len_field(tag: int, payload: bytes) -> bytes:
    return bytes([tag]) + _varint(len(payload)) + payload


def _encode_feature(field: Field, value) -> bytes:
    """A ``tf.train.Feature`` message for ``value`` (validated against ``field``)."""
    if field.kind == "string":
        if isinstance(value, str):
            value = value.encode("utf-8")
        elif isinstance(value, np.ndarray):
            value = value.item()
            value = value.encode("utf-8") if isinstance(value, str) else bytes(value)
        if not isinstance(value, (bytes, bytearray)):
            raise ValueError(f"{field.name} must be str or bytes; received {type(value).__name__}.")
        return _len_field(0x0A, _len_field(0x0A, bytes(value)))  # bytes_list { value }
    arr = np.asarray(value)
    if arr.size != field.size:
        raise ValueError(f"{field.name} must have {field.size} elements (shape {list(field.shape)})"
                         f"; received shape {arr.shape}.")
    if field.kind == "raw":
        if arr.dtype != np.uint8:
            raise ValueError(f"{field.name} must be uint8; received {arr.dtype}.")
        return _len_field(0x0A, _len_field(0x0A, np.ascontiguousarray(arr).tobytes()))
    if field.kind == "float":
        data = np.ascontiguousarray(arr, dtype="<f4").tobytes()
        return _len_field(0x12, _len_field(0x0A, data))  # float_list { packed value }
    if field.kind == "int64":
        data = b"".join(_varint(int(v)) for v in arr.reshape(-1))
        return _len_field(0x1A, _len_field(0x0A, data))  # int64_list { packed value }
    raise AssertionError(field.kind)


def serialize_example(sample: dict) -> bytes:
    """A dict of NumPy values -> serialized ``tf.train.Example`` bytes.

    ``sample`` must hold every name of :data:`FEATURE_NAMES` (extra keys are ignored). Numeric
    values may have any shape with the right number of elements (``h_ba`` ``[3, 3]`` or ``[9]``);
    float values are stored as float32, patches must be uint8.

    Raises:
      ValueError: a missing field, a wrong element count or dtype (naming the field).
    """
    missing = [n for n in FEATURE_NAMES if n not in sample]
    if missing:
        raise ValueError(f"sample lacks feature(s) {missing}; it must hold {list(FEATURE_NAMES)}.")
    entries = []
    for name in sorted(FEATURE_NAMES):
        key = name.encode("utf-8")
        entry = _len_field(0x0A, key) + _len_field(0x12, _encode_feature(FIELD_BY_NAME[name],
                                                                          sample[name]))
        entries.append(_len_field(0x0A, entry))  # map<string, Feature> feature = 1
    return _len_field(0x0A, b"".join(entries))  # Example.features = 1


def _read_varint(buf: bytes, pos: int):
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


def _fields(buf: bytes):
    """Yield ``(field_number, wire_type, value)`` of a protobuf message (value: int or bytes)."""
    pos, n = 0, len(buf)
    while pos < n:
        key, pos = _read_varint(buf, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _read_varint(buf, pos)
        elif wire == 2:
            length, pos = _read_varint(buf, pos)
            if pos + length > n:
                raise ValueError("truncated length-delimited field")
            value, pos = buf[pos:pos + length], pos + length
        elif wire == 5:
            value, pos = buf[pos:pos + 4], pos + 4
        elif wire == 1:
            value, pos = buf[pos:pos + 8], pos + 8
        else:
            raise ValueError(f"unsupported wire type {wire}")
        yield number, wire, value


def _decode_feature(field: Field, msg: bytes):
    values = []
    for number, _, lst in _fields(msg):
        if number == 1:  # bytes_list
            values += [v for num, _, v in _fields(lst) if num == 1]
        elif number == 2:  # float_list (packed or not)
            for num, wire, v in _fields(lst):
                if num == 1:
                    values += list(np.frombuffer(v, "<f4"))
        elif number == 3:  # int64_list (packed or not)
            for num, wire, v in _fields(lst):
                if num != 1:
                    continue
                if wire == 0:
                    values.append(v)
                else:
                    pos = 0
                    while pos < len(v):
                        x, pos = _read_varint(v, pos)
                        values.append(x)
    if field.kind == "string":
        if len(values) != 1:
            raise ValueError(f"{field.name}: expected one bytes value, found {len(values)}")
        return values[0].decode("utf-8")
    if field.kind == "raw":
        if len(values) != 1 or len(values[0]) != field.size:
            raise ValueError(f"{field.name}: expected {field.size} bytes")
        return np.frombuffer(values[0], np.uint8).reshape(field.shape).copy()
    if len(values) != field.size:
        raise ValueError(f"{field.name}: expected {field.size} values, found {len(values)}")
    if field.kind == "int64":
        values = [v - (1 << 64) if v >= 1 << 63 else v for v in values]
    return np.array(values, dtype=field.numpy_dtype).reshape(field.shape)


def decode_example(serialized: bytes, names=None) -> dict:
    """Serialized ``tf.train.Example`` -> dict of NumPy values, without TensorFlow.

    Raw fields become uint8 arrays of their spec shape, floats float32, ints int64, ``image_id``
    a ``str``. ``names`` restricts the fields returned (default: all of :data:`FEATURE_NAMES`).

    Raises:
      ValueError: malformed bytes or a missing/mis-sized feature.
    """
    wanted = set(FEATURE_NAMES if names is None else names)
    raw = {}
    for number, _, features in _fields(bytes(serialized)):
        if number != 1:
            continue
        for num, _, entry in _fields(features):
            if num != 1:
                continue
            key, value = None, b""
            for n, _, v in _fields(entry):
                if n == 1:
                    key = v.decode("utf-8")
                elif n == 2:
                    value = v
            if key in wanted:
                raw[key] = value
    missing = sorted(wanted - raw.keys())
    if missing:
        raise ValueError(f"example lacks feature(s) {missing}")
    return {name: _decode_feature(FIELD_BY_NAME[name], raw[name]) for name in wanted}


# ------------------------------------------------------------------------------------------------
# TensorFlow parser
# ------------------------------------------------------------------------------------------------
def tf_feature_spec(names=None) -> dict:
    """``{name: tf.io.FixedLenFeature}`` for ``tf.io.parse_example`` (all fields by default)."""
    import tensorflow as tf

    dtype = {"raw": tf.string, "string": tf.string, "float": tf.float32, "int64": tf.int64}
    out = {}
    for name in FEATURE_NAMES if names is None else names:
        f = FIELD_BY_NAME[name]
        shape = [] if f.kind in ("raw", "string") else list(f.shape)
        out[name] = tf.io.FixedLenFeature(shape, dtype[f.kind])
    return out


def parse_examples(serialized, names=None) -> dict:
    """TensorFlow parser: serialized records ``[...]`` (scalar or batch) -> dict of tensors.

    Raw fields are decoded to uint8 ``[..., *shape]`` (e.g. ``[B, 128, 128]``), ``h_bar``
    float32 ``[..., 8]``, ``h_ba``/``h_prev`` float32 ``[..., 3, 3]``, ``h_mask`` float32
    ``[...]``, ``square_xy`` int64 ``[..., 2]``, ``image_id`` string ``[...]``, ``index`` int64.
    Works inside ``tf.data`` maps.
    """
    import tensorflow as tf

    names = FEATURE_NAMES if names is None else tuple(names)
    parsed = tf.io.parse_example(serialized, tf_feature_spec(names))
    lead = tf.shape(serialized)
    out = {}
    for name in names:
        f, v = FIELD_BY_NAME[name], parsed[name]
        if f.kind == "raw":
            v = tf.io.decode_raw(v, tf.uint8, fixed_length=f.size)
            v = tf.reshape(v, tf.concat([lead, list(f.shape)], axis=0))
        elif name in ("h_ba", "h_prev"):
            v = tf.reshape(v, tf.concat([lead, [3, 3]], axis=0))
        out[name] = v
    return out
