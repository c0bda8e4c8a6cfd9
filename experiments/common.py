"""Small helpers shared by the benchmark and evaluation binaries (no flags defined here)."""

from __future__ import annotations

import json


def emit_json(result: dict, json_out: str | None = None) -> None:
    """Print ``result`` as indented JSON and, if ``json_out`` is given, write it there too."""
    text = json.dumps(result, indent=2)
    print(text)
    if json_out:
        with open(json_out, "w") as f:
            f.write(text + "\n")
