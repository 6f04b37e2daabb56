"""The platform's configuration: one YAML document validated against the JSON schema.

The schema (``workflow/schemas/config.schema.yaml``, shipped in the package as
``dozerlab/config.schema.yaml``) gives every field a default, so a partial document is
valid and comes back complete. Invalid values are refused with the field's dotted name and
the allowed range before any work starts.
"""

from __future__ import annotations

import copy
import json
import warnings
from collections.abc import Mapping
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import yaml
from jsonschema.protocols import Validator

from dozerlab.runtime import DozerlabError


class ConfigError(DozerlabError, ValueError):
    """A configuration value outside what the schema allows."""


class ConfigWarning(UserWarning):
    """A valid configuration that sets up an unphysical scene."""


#: Lateral gaps between blade end and side wall, in mean grain diameters, from which grains no
#: longer jam there: with a 1-diameter gap on the default sweep they wedged and dragged along
#: the walls, a third of the pushing force and ±2 kN sideways, outside the sampling volume; with
#: 3 diameters the sideways force fell to 0.2 kN (BENCHMARKS.md).
FREE_GAP_DIAMETERS = 3.0


def check_geometry(config: Mapping[str, Any]) -> None:
    """Warn (:class:`ConfigWarning`) when a grain fits between the blade's ends and the side
    walls but the gap is narrower than ``FREE_GAP_DIAMETERS`` mean diameters: grains wedge there.
    ``config`` is a validated document."""
    bed, blade = config["bed"], config["blade"]
    gap = 0.5 * (bed["width"] - blade["width"])
    diameter = 2.0 * bed["radius"]
    smallest = diameter * (1.0 - bed["radius_dispersion"])
    if smallest <= gap < FREE_GAP_DIAMETERS * diameter:
        warnings.warn(
            f"config fields 'bed.width' and 'blade.width': the {gap:.3g} m gap between each blade end "
            f"and side wall is {gap / diameter:.2g} grain diameters; grains wedge in it and drag on the "
            f"walls, a force the fields in front of the blade do not see (make it < {smallest:.3g} m, "
            f"the smallest grain, or >= {FREE_GAP_DIAMETERS * diameter:.3g} m)",
            ConfigWarning,
            stacklevel=3,
        )


@cache
def schema() -> dict[str, Any]:
    """The configuration's JSON schema as a dict."""
    text = resources.files("dozerlab").joinpath("config.schema.yaml").read_text()
    return yaml.safe_load(text)


def _with_defaults(cls: type[Validator]) -> type[Validator]:
    """Extend a jsonschema validator class so that it fills in defaults while validating."""
    validate_properties = cls.VALIDATORS["properties"]

    def properties(validator, props, instance, sch):
        if isinstance(instance, dict):
            for name, sub in props.items():
                if "default" in sub:
                    instance.setdefault(name, copy.deepcopy(sub["default"]))
        yield from validate_properties(validator, props, instance, sch)

    return jsonschema.validators.extend(cls, {"properties": properties})


_Validator = _with_defaults(jsonschema.Draft202012Validator)


def _allowed(error: jsonschema.ValidationError) -> str:
    """The constraint that failed, said as an allowed range or set."""
    v, kind = error.validator_value, error.validator
    return {
        "minimum": f"allowed: >= {v}",
        "exclusiveMinimum": f"allowed: > {v}",
        "maximum": f"allowed: <= {v}",
        "exclusiveMaximum": f"allowed: < {v}",
        "enum": f"allowed: one of {v}",
        "type": f"allowed: a value of type {v}",
        "additionalProperties": "allowed: only the fields the schema lists",
        "minItems": f"allowed: at least {v} items",
        "maxItems": f"allowed: at most {v} items",
        "required": f"required fields: {v}",
    }.get(kind, f"constraint {kind}: {v}")


def validate(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """Validate ``config`` and return a deep copy with every default filled in.

    Raises :class:`ConfigError` naming the field (dotted path) and its allowed range.
    """
    doc = copy.deepcopy(dict(config or {}))
    errors = sorted(_Validator(schema()).iter_errors(doc), key=lambda e: list(e.absolute_path))
    if errors:
        lines = []
        for e in errors:
            field = ".".join(str(p) for p in e.absolute_path) or "<top level>"
            lines.append(f"config field '{field}': {e.message} ({_allowed(e)})")
        raise ConfigError("invalid configuration:\n  " + "\n  ".join(lines))
    check_geometry(doc)
    return doc


def load_config(source: str | Path | Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Load and validate a configuration.

    ``source`` is a mapping, a path to a YAML/JSON file, an inline JSON object string (what the
    workflow's rules pass), or None for all defaults.
    """
    if source is None or isinstance(source, Mapping):
        return validate(source)
    text = str(source)
    if text.lstrip().startswith("{"):
        try:
            return validate(json.loads(text))
        except json.JSONDecodeError as exc:
            raise ConfigError(f"inline configuration is not valid JSON: {exc}") from exc
    path = Path(text)
    if not path.is_file():
        raise ConfigError(f"configuration file not found: {path}")
    return validate(yaml.safe_load(path.read_text()) or {})
