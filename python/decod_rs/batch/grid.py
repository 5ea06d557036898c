"""A sweep's grid: parameters, their values, the settings they make, and which of them
change extraction.

A parameter is a dotted config key (``matching.min_inliers``; ``decod dump-config`` lists
them all). The settings are the Cartesian product of the values, in the order the
parameters were given. Only the ``submap``, ``axis``, ``contour``, ``boundary`` and
``descriptor`` sections reach the Rust ``LogProcessor`` (extraction); ``matching`` and
``graph`` are read after it (:data:`REPLAYED_SECTIONS`), so settings that differ only there
share one extraction per log (:func:`extraction_params`).

Acceptance: ``matching.min_inliers`` acts only under ``matching.acceptance = "fixed"`` (the
paper's ``K >= K_thresh``), ``matching.false_alarm_rate`` only under ``"null_model"`` (the
default). A grid that sweeps one of them without giving ``matching.acceptance`` gets the
acceptance under which it acts (:func:`implied_acceptance`); sweeping both needs
``matching.acceptance`` in the grid.
"""

from __future__ import annotations

import itertools
import json
import math
import tomllib
from dataclasses import dataclass
from typing import Any

from decod_rs import _core
from decod_rs.config import Config

#: Config sections read only after extraction (matching, selection, the pose graph).
REPLAYED_SECTIONS = ("matching", "graph")
#: Far more settings than a calibration needs (the paper's tables: 2 thresholds); a bigger
#: grid is more likely a mistake than a plan.
MAX_SETTINGS = 1000
ACCEPTANCE_KEY = "matching.acceptance"
#: The parameter -> the acceptance under which it acts.
ACCEPTANCE_OF = {"matching.min_inliers": "fixed", "matching.false_alarm_rate": "null_model"}

__all__ = [
    "MAX_SETTINGS",
    "REPLAYED_SECTIONS",
    "Setting",
    "apply_params",
    "check_params",
    "extraction_params",
    "implied_acceptance",
    "parse_param",
    "settings_from_grid",
]


@dataclass(frozen=True)
class Setting:
    """One point of the grid: ``id`` (``s00``, ...; its output directory) and its parameter
    values (dotted key -> value), the implied acceptance included."""

    id: str
    params: dict[str, Any]

    def label(self) -> str:
        return ", ".join(f"{k.split('.', 1)[-1]}={v}" for k, v in self.params.items())


def _scalar(text: str) -> Any:
    """A command-line value as TOML reads it (``9``, ``1e-3``, ``true``, ``"x"``); a bare
    word is a string (``fixed``)."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_param(text: str) -> tuple[str, list[Any]]:
    """``KEY=V1,V2,...`` (``matching.min_inliers=6,9,15``) -> (key, values)."""
    key, sep, values = text.partition("=")
    key = key.strip()
    if not sep or "." not in key or not values.strip():
        raise ValueError(
            f"--param {text!r}: expected SECTION.KEY=V1,V2,... (e.g. matching.min_inliers=6,9)"
        )
    return key, [_scalar(v.strip()) for v in values.split(",")]


def implied_acceptance(grid: dict[str, list[Any]]) -> str | None:
    """The acceptance the grid's parameters need (module doc), or None."""
    if ACCEPTANCE_KEY in grid:
        return None
    needed = {ACCEPTANCE_OF[k] for k in grid if k in ACCEPTANCE_OF}
    if len(needed) > 1:
        raise ValueError(
            "the grid sweeps matching.min_inliers (acts under acceptance 'fixed') and "
            "matching.false_alarm_rate (acts under 'null_model'): add "
            "matching.acceptance to the grid"
        )
    return needed.pop() if needed else None


def settings_from_grid(grid: dict[str, list[Any]]) -> list[Setting]:
    """Every combination of the grid's values, ``s00``, ``s01``, ... (first key slowest)."""
    if not grid:
        raise ValueError("empty grid: give --param KEY=V1,V2 or a manifest [sweep] table")
    total = math.prod(len(v) for v in grid.values())
    if total > MAX_SETTINGS:
        raise ValueError(f"the grid has {total} settings, more than {MAX_SETTINGS}")
    acceptance = implied_acceptance(grid)
    width = max(2, len(str(total - 1)))
    settings = []
    for k, combo in enumerate(itertools.product(*grid.values())):
        params = dict(zip(grid, combo, strict=True))
        if acceptance is not None:
            params[ACCEPTANCE_KEY] = acceptance
        settings.append(Setting(f"s{k:0{width}d}", params))
    return settings


def _toml_value(value: Any) -> str:
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return json.dumps(value)


def _toml(values: dict[str, Any]) -> str:
    lines = [f"{k} = {_toml_value(v)}" for k, v in values.items() if not isinstance(v, dict)]
    for section, table in values.items():
        if isinstance(table, dict):
            lines.append(f"[{section}]")
            lines.extend(f"{k} = {_toml_value(v)}" for k, v in table.items())
    return "\n".join(lines) + "\n"


def _nested(params: dict[str, Any]) -> dict[str, dict[str, Any]]:
    tables: dict[str, dict[str, Any]] = {}
    for key, value in params.items():
        section, _, name = key.partition(".")
        if not name or "." in name:
            raise _core.ConfigError(f"invalid config `{key}`: expected SECTION.KEY")
        tables.setdefault(section, {})[name] = value
    return tables


def apply_params(cfg: Config, params: dict[str, Any]) -> Config:
    """``cfg`` with ``params`` (dotted key -> value) set, resolved and checked by the Rust
    config (an unknown key or a bad value is a ``ConfigError`` naming it). The result is
    what ``run_log`` gets from a TOML file holding ``params``."""
    values = cfg.to_dict()
    for section, table in _nested(params).items():
        values.setdefault(section, {}).update(table)
    preset = values.get("preset", "tunnel")
    return Config(json.loads(_core.resolve_config_json(str(preset), _toml(values))))


def check_params(settings: list[Setting], preset: str) -> None:
    """Resolve every setting on ``preset``'s defaults (``tunnel`` for ``auto``) so that a
    misspelt parameter stops the sweep before any log runs."""
    base = "tunnel" if preset == "auto" else preset
    for setting in settings:
        _core.resolve_config_json(base, _toml(_nested(setting.params)))


def extraction_params(params: dict[str, Any]) -> tuple[tuple[str, str], ...]:
    """The parameters that reach extraction (not :data:`REPLAYED_SECTIONS`), as a sortable
    key: settings with equal keys share one extraction of a log."""
    return tuple(
        sorted(
            (k, json.dumps(v))
            for k, v in params.items()
            if k.partition(".")[0] not in REPLAYED_SECTIONS
        )
    )


def params_toml(params: dict[str, Any]) -> str:
    """``params`` as a ``--config`` TOML file (what a single ``decod run`` at this setting
    would be given)."""
    return _toml(_nested(params))
