"""The configuration: one section per pipeline stage, defaults from the Rust core.

The Rust ``DecodConfig`` is the single source of every default (``src/config.rs``); this
module resolves a preset plus an optional TOML file into a nested mapping with attribute
access, so ``cfg.matching.min_inliers`` reads like the TOML it came from.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from decod_rs import _core

PRESETS = ("tunnel", "pipe")
#: Matching modes of a run (``decod run --mode``): ``auto`` is ``batch`` (return landmarks query
#: the outbound) when the trajectory has a return leg, else ``online`` (:mod:`decod_rs.pipeline`).
MODES = ("auto", "batch", "online")


class Config:
    """A read-only view of one resolved config section (or the whole config)."""

    def __init__(self, values: dict[str, Any], path: str = "") -> None:
        self._values = values
        self._path = path

    def __getattr__(self, name: str) -> Any:
        try:
            value = self._values[name]
        except KeyError:
            where = self._path or "config"
            raise AttributeError(f"{where} has no parameter {name!r}") from None
        if isinstance(value, dict):
            return Config(value, f"{self._path}.{name}" if self._path else name)
        return value

    def to_dict(self) -> dict[str, Any]:
        """A deep copy as plain dicts (JSON-serialisable)."""
        return json.loads(json.dumps(self._values))

    def __repr__(self) -> str:
        return f"Config({self._path or 'root'}: {sorted(self._values)})"


def load_config(path: str | Path | None = None, preset: str = "tunnel") -> Config:
    """Resolve ``preset`` overridden by the TOML file at ``path`` (if any).

    Unknown keys and out-of-range values raise ``ConfigError`` naming the parameter.
    """
    if preset not in PRESETS:
        raise _core.ConfigError(f"invalid config `preset`: {preset!r} is not one of {PRESETS}")
    overrides = ""
    if path is not None:
        overrides = Path(path).read_text(encoding="utf-8")
    return Config(json.loads(_core.resolve_config_json(preset, overrides)))


def dump_config(preset: str = "tunnel") -> str:
    """Every parameter of ``preset`` with its default, as TOML."""
    if preset not in PRESETS:
        raise _core.ConfigError(f"invalid config `preset`: {preset!r} is not one of {PRESETS}")
    return _core.default_config_toml(preset)
