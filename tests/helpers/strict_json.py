"""Strict JSON reading for tests: what jq and JavaScript accept (no NaN or Infinity)."""

import json


def strict_loads(text: str):
    """``json.loads`` that refuses NaN, Infinity and -Infinity."""

    def refuse(name):
        raise ValueError(f"not strict JSON: {name}")

    return json.loads(text, parse_constant=refuse)
