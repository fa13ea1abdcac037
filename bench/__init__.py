"""Benchmarks (`make bench`): each writes one JSON under bench/results."""
from __future__ import annotations

import json
from pathlib import Path


def write_result(path, result: dict, indent: int = 2) -> None:
    """Write ``result`` as JSON to ``path`` (its folder made where missing) and print it."""
    text = json.dumps(result, indent=indent)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(text)
    print(text)
