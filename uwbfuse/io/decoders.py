# SPDX-License-Identifier: BSD-3-Clause
"""Generic (per-message) decoders, chosen from a registry by the channel's message encoding.

- `cdr`: ROS 2 CDR, decoded from the `ros2msg` schema embedded in the file by
  `mcap_ros2.decoder.DecoderFactory` (any message type, nested and array fields included);
  messages are objects with attributes.
- `json`: JSON text (schema encoding `jsonschema` or none); messages are dicts.

Fixed-layout ROS 2 types take the vectorised path in `cdr_fast` first; these decoders see
only what that path cannot read.
"""

from __future__ import annotations

import contextlib
import io
import json
from collections.abc import Callable
from typing import Any

from mcap.records import Schema

from uwbfuse.io import ros2msg
from uwbfuse.io.mcap_raw import RawChannel

DecodeFn = Callable[[bytes], Any]


class DecoderUnavailable(Exception):
    """No decoder for a channel (unknown encoding, missing or unparsable schema)."""


def _cdr(channel: RawChannel) -> DecodeFn:
    from mcap_ros2.decoder import DecoderFactory

    schema = channel.schema
    if schema is None:
        raise DecoderUnavailable("cdr messages without a schema cannot be decoded")
    if schema.encoding != "ros2msg":
        raise DecoderUnavailable(f"schema encoding {schema.encoding!r} is not supported "
                                 "for cdr (only ros2msg)")
    record = Schema(id=schema.id, name=schema.name, encoding=schema.encoding, data=schema.data)
    text = schema.data.decode("utf-8", errors="replace")
    try:
        ros2msg.layout_of(schema.name, text)  # recursion, depth and size bombs first
        # the vendored rosidl parser prints some of its complaints: keep them off the
        # terminal (the error below says what was wrong)
        with contextlib.redirect_stdout(io.StringIO()), \
                contextlib.redirect_stderr(io.StringIO()):
            fn = DecoderFactory().decoder_for("cdr", record)
    except Exception as e:  # the vendored rosidl parser raises many types
        why = " ".join(str(e).split())[:200]
        raise DecoderUnavailable(f"cannot parse schema {schema.name!r}: {why}") from None
    if fn is None:
        raise DecoderUnavailable(f"no cdr decoder for schema {schema.name!r}")
    return fn


def _json(channel: RawChannel) -> DecodeFn:
    if channel.schema is not None and channel.schema.encoding not in ("jsonschema", ""):
        raise DecoderUnavailable(f"schema encoding {channel.schema.encoding!r} is not "
                                 "supported for json (only jsonschema)")
    return json.loads


DECODERS: dict[str, Callable[[RawChannel], DecodeFn]] = {"cdr": _cdr, "json": _json}


def generic_decoder(channel: RawChannel) -> DecodeFn:
    """A bytes -> message function for `channel`; raises DecoderUnavailable."""
    factory = DECODERS.get(channel.message_encoding)
    if factory is None:
        raise DecoderUnavailable(
            f"message encoding {channel.message_encoding!r} is not supported (cdr or json)"
        )
    return factory(channel)
