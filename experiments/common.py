"""Small helpers shared by the binaries (no flags defined here): the JSON they print, and how a
user's error ends them."""

from __future__ import annotations

import contextlib
import json

from stnh_tf import provenance  # noqa: F401  (records the commit and load at the binary's start)
from stnh_tf.paths import atomic_write_text


def emit_json(result: dict, json_out: str | None = None) -> None:
    """Print ``result`` as indented JSON and, if ``json_out`` is given, write it there too."""
    text = json.dumps(result, indent=2)
    print(text)
    if json_out:
        atomic_write_text(json_out, text + "\n")


@contextlib.contextmanager
def user_errors(binary: str, errors=(ValueError, OSError)):
    """Turn ``errors`` raised inside into ``SystemExit("<binary>: <message>")``: a user's mistake
    (a bad flag, a missing file) ends a binary with one line, not a traceback."""
    try:
        yield
    except errors as e:
        raise SystemExit(f"{binary}: {e}") from None
