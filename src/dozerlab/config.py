"""The platform's configuration: one YAML document validated against the JSON schema.

The schema (``workflow/schemas/config.schema.yaml``, shipped in the package as
``dozerlab/config.schema.yaml``) gives every field a default, so a partial document is
valid and comes back complete. Invalid values are refused with the field's dotted name and
the allowed range before any work starts.
"""

from __future__ import annotations

import copy
import io
import json
import math
import os
import re
import warnings
from collections.abc import Hashable, Iterable, Mapping
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import yaml
from jsonschema.protocols import Validator

from dozerlab.runtime import ConfigError


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
    """Extend a jsonschema validator class so that it fills in defaults while validating, takes
    only whole numbers of type ``int`` as integers (``3.0`` and ``true`` are refused: a count
    that is a float fails later, far from its field) and refuses NaN and ±inf where a number is
    asked for (they pass every range check: NaN compares false)."""
    validate_properties = cls.VALIDATORS["properties"]
    validate_type = cls.VALIDATORS["type"]

    def properties(validator, props, instance, sch):
        if isinstance(instance, dict):
            for name, sub in props.items():
                if "default" in sub:
                    instance.setdefault(name, copy.deepcopy(sub["default"]))
        yield from validate_properties(validator, props, instance, sch)

    def type_(validator, types, instance, sch):
        if isinstance(instance, float) and not math.isfinite(instance):
            yield jsonschema.ValidationError(
                f"{instance} is not a finite number", validator="finite", validator_value=None
            )
            return
        yield from validate_type(validator, types, instance, sch)

    checker = cls.TYPE_CHECKER.redefine(
        "integer", lambda _, v: isinstance(v, int) and not isinstance(v, bool)
    )
    return jsonschema.validators.extend(
        cls, {"properties": properties, "type": type_}, type_checker=checker
    )


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
        "type": "allowed: a whole number, written without a point (3, not 3.0)"
        if v == "integer"
        else f"allowed: a value of type {v}",
        "additionalProperties": "allowed: only the fields the schema lists",
        "minItems": f"allowed: at least {v} items",
        "maxItems": f"allowed: at most {v} items",
        "required": f"required fields: {v}",
        "uniqueItems": "allowed: each value once",
        "finite": "allowed: a finite number",
    }.get(kind, f"constraint {kind}: {v}")


def field_name(path: Iterable[str | int]) -> str:
    """The name of a field in messages: keys dotted, list positions in brackets
    (``sweep.speeds[0]``, ``sweep.interpolation[1].depth``)."""
    name = ""
    for part in path:
        name += f"[{part}]" if isinstance(part, int) else f".{part}" if name else str(part)
    return name or "<top level>"


#: A number as YAML 1.2 writes it. PyYAML (YAML 1.1, also Snakemake's loader) reads ``1e9``
#: or ``1E-3`` (no point) as a string; :func:`validate` reads such strings as numbers where the
#: schema asks for one.
_YAML12_NUMBER = re.compile(r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")


def _numbers(doc: Any, sch: Mapping[str, Any]) -> Any:
    """``doc`` with number-like strings made floats wherever ``sch`` expects a number."""
    if isinstance(doc, dict):
        props = sch.get("properties", {})
        return {k: _numbers(v, props[k]) if k in props else v for k, v in doc.items()}
    if isinstance(doc, list) and isinstance(sch.get("items"), Mapping):
        return [_numbers(v, sch["items"]) for v in doc]
    if isinstance(doc, str) and sch.get("type") == "number" and _YAML12_NUMBER.fullmatch(doc):
        return float(doc)
    return doc


def check_cuts(config: Mapping[str, Any]) -> None:
    """Refuse cut depths that reach within a grain diameter of the ground anywhere along a path.

    The tip follows the bed height minus the depth wherever the bed is at or above the goal
    height (docs/physics.md), so its lowest point is (the higher of the bed's lowest level and the goal
    height) minus the depth; a path clamped to the ground crushes grains against it and the
    run diverges.
    """
    from dozerlab.terrain import lowest_level  # here, not at the top: it imports numpy

    margin = 2.0 * config["bed"]["radius"]
    sweep = config["sweep"]
    cuts = [
        (f"sweep.depths[{i}]", s, d)
        for s in sweep["scenarios"]
        for i, d in enumerate(sweep["depths"])
    ]
    for role in ("interpolation", "extrapolation", "transfer"):
        cuts += [
            (f"sweep.{role}[{i}].depth", p["scenario"], p["depth"])
            for i, p in enumerate(sweep[role])
        ]
    for field, scenario, depth in cuts:
        if scenario not in config["scenarios"]:
            continue  # a job given the sweep, not the user's scenarios (check_scenario_names)
        shape = config["scenarios"][scenario]
        low, lowest = lowest_level(scenario, config)
        level = max(lowest, shape["goal_height"])
        if depth > level - margin:
            raise ConfigError(
                f"config field '{field}': a {depth} m cut is deeper than the {scenario} bed allows: "
                f"where the blade cuts, the bed is at least {level} m high "
                f"({low} {lowest} m, goal_height {shape['goal_height']} m), and "
                f"the tip must stay a grain diameter (2 × bed.radius = {margin:.3g} m) above the ground "
                f"(allowed: depth <= {level - margin:.4g} m)"
            )


def height_bound() -> float:
    """The highest ground height a bed may have (m), the top of the bed's box: the schema's
    bound on every preset height."""
    hill = schema()["properties"]["scenarios"]["properties"]["hill"]["properties"]
    return float(hill["peak_height"]["maximum"])


def check_scenario_names(config: Mapping[str, Any]) -> None:
    """Refuse a sweep point on a scenario the config's ``scenarios`` section does not define
    (the presets always are), and a transfer point on a scenario of the training grid."""
    sweep = config["sweep"]
    named = [(f"sweep.scenarios[{i}]", s) for i, s in enumerate(sweep["scenarios"])]
    for role in ("interpolation", "extrapolation", "transfer"):
        named += [(f"sweep.{role}[{i}].scenario", p["scenario"]) for i, p in enumerate(sweep[role])]
    for field, name in named:
        if name not in config["scenarios"]:
            raise ConfigError(
                f"config field '{field}': scenario '{name}' is not defined (allowed: one of "
                f"{sorted(config['scenarios'])}, or a scenario added under scenarios)"
            )


#: Bytes per bin and sampled step: velocity (3) and density (1), float32.
_BIN_BYTES = 16


def memory_estimate(config: Mapping[str, Any]) -> dict[str, float]:
    """Peak memory in bytes of the largest jobs, estimated from the config alone.

    ``simulate`` holds a chunk of ``sampling.chunk_steps`` steps of fields and a few steps of
    sampling temporaries; ``train`` holds every training store whole and a concatenated copy.
    A run's steps are at most the bed's length at the blade's speed, sampled every
    ``sampling.every`` steps.
    """
    s, sweep = config["sampling"], config["sweep"]
    nx, ny, nz = s["bins"]
    cells = (nx + s["behind_bins"]) * (ny + 2 * s["side_bins"]) * (nz + s["above_bins"])
    dt, length = config["solver"]["dt"], config["bed"]["length"]
    steps = [length / (v * dt) / s["every"] for v in sweep["speeds"]]
    runs = len(sweep["scenarios"]) * len(sweep["depths"])
    return {
        "simulate": (s["chunk_steps"] + 8) * cells * _BIN_BYTES,
        "train": 2 * runs * sum(steps) * cells * _BIN_BYTES,
    }


def machine_memory() -> int:
    """This machine's physical memory in bytes."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_memory(
    config: Mapping[str, Any],
    available: int | None = None,
    jobs: tuple[str, ...] = ("simulate", "train"),
) -> None:
    """Refuse bins and steps whose ``jobs`` would need more memory than the machine has."""
    available = machine_memory() if available is None else available
    fields = {
        "simulate": "sampling.bins and sampling.chunk_steps",
        "train": "sampling.bins and the steps per run (bed.length / (sweep.speeds × solver.dt) / "
        "sampling.every) over the training grid",
    }
    for job, need in memory_estimate(config).items():
        if job in jobs and need > available:
            raise ConfigError(
                f"config fields {fields[job]}: a {job} job would need about {need / 2**30:.3g} GiB of "
                f"memory (bins {config['sampling']['bins']}), more than this machine's "
                f"{available / 2**30:.3g} GiB (allowed: an estimate within the machine's memory)"
            )


def validate(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """Validate ``config`` and return a deep copy with every default filled in.

    Beyond the schema: cuts deeper than the beds allow (:func:`check_cuts`), jobs larger than
    the machine's memory (:func:`check_memory`), held-out points that are training points
    (:func:`dozerlab.sweep.sweep_points`). Numbers YAML 1.1 reads as strings (``1e9``) are
    numbers. Raises :class:`ConfigError` naming the field (dotted path) and its allowed range.
    """
    if config is not None and not isinstance(config, Mapping):
        raise ConfigError(
            f"a configuration must be a mapping of sections, got {type(config).__name__}"
        )
    doc = _numbers(copy.deepcopy(dict(config or {})), schema())
    errors = sorted(_Validator(schema()).iter_errors(doc), key=lambda e: list(e.absolute_path))
    # a non-finite number breaks its bounds too: say only that it is not finite
    infinite = {tuple(e.absolute_path) for e in errors if e.validator == "finite"}
    errors = [
        e for e in errors if e.validator == "finite" or tuple(e.absolute_path) not in infinite
    ]
    if errors:
        lines = []
        for e in errors:
            field = field_name(e.absolute_path)
            lines.append(f"config field '{field}': {e.message} ({_allowed(e)})")
        raise ConfigError("invalid configuration:\n  " + "\n  ".join(lines))
    # A job gets only the sections it reads (the rest are defaults): the sweep's checks apply
    # where a sweep is given, so a default sweep never fails against a user's bed.
    # Terrain is checked against the bed it is built in, where the document gives it (the
    # trajectory job reads a scenario's goal height only); build_bed checks it again.
    if {"scenarios", "bed"} <= set(config or {}):
        from dozerlab.terrain import check_scenarios

        check_scenarios(doc, height_bound())
    if "sweep" in (config or {}):
        from dozerlab.sweep import sweep_points  # here, not at the top: it imports numpy

        sweep_points(doc)
        check_scenario_names(doc)
        check_cuts(doc)
    check_memory(doc, jobs=("simulate", "train") if "sweep" in (config or {}) else ("simulate",))
    # and the gap check where both bed and blade are given: the reduce job, given the blade but
    # not the bed, warned of the default bed's gap in every log
    if {"bed", "blade"} <= set(config or {}):
        check_geometry(doc)
    if {"dynamics", "sampling"} <= set(config or {}):
        check_ridge_bands(doc)
    return doc


def check_ridge_bands(config: Mapping[str, Any]) -> None:
    """Refuse ridge band edges (``dynamics.ridge_y_bands``, ``ridge_z_bands``) that do not
    increase within the sampling volume's columns and rows. ``config`` is a validated document."""
    s = config["sampling"]
    sizes = {
        "ridge_y_bands": s["bins"][1] + 2 * s["side_bins"],
        "ridge_z_bands": s["bins"][2] + s["above_bins"],
    }
    for key, n in sizes.items():
        edges = list(config["dynamics"][key])
        if edges != sorted(edges) or any(not 0 < e < n for e in edges):
            raise ConfigError(
                f"config field 'dynamics.{key}': {edges} (allowed: increasing bin edges within "
                f"1..{n - 1}, the sampling volume's {n} bins)"
            )


class _DuplicateKey(yaml.YAMLError):
    """A mapping of a YAML document gives ``key`` on ``lines`` (1-based) both."""

    def __init__(self, key: Any, lines: tuple[int, int]) -> None:
        super().__init__(key, lines)
        self.key, self.lines = key, lines


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader that refuses a key given twice in one mapping (PyYAML keeps the
    last silently, so a repeated section would drop the first one's fields unseen)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            line = key_node.start_mark.line + 1
            if isinstance(key, Hashable) and key in seen:
                raise _DuplicateKey(key, (seen[key], line))
            if isinstance(key, Hashable):
                seen[key] = line
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | Path) -> Any:
    """The YAML document of the configuration file ``path``, not yet validated.

    Raises :class:`ConfigError` naming the file when it is missing, not UTF-8 text, not valid
    YAML or gives a key twice in one mapping.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"configuration file not found: {path}")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"configuration file {path} is not UTF-8 text (byte {exc.start} is 0x{exc.object[exc.start]:02x}); "
            "a configuration is a YAML document"
        ) from None
    stream = io.StringIO(text)
    stream.name = str(path)  # PyYAML's messages name the stream
    try:
        return yaml.load(stream, Loader=_UniqueKeyLoader)  # a SafeLoader
    except _DuplicateKey as exc:
        raise ConfigError(
            f"configuration file {path} gives the key '{exc.key}' twice in one mapping (lines "
            f"{exc.lines[0]} and {exc.lines[1]}; allowed: each key once)"
        ) from None
    except yaml.YAMLError as exc:
        detail = " ".join(str(exc).split())
        raise ConfigError(f"configuration file {path} is not valid YAML: {detail}") from None


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object's pairs as a dict, refusing a key given twice."""
    doc: dict[str, Any] = {}
    for key, value in pairs:
        if key in doc:
            raise ConfigError(
                f"inline configuration gives the key '{key}' twice (allowed: each key once)"
            )
        doc[key] = value
    return doc


def load_config(source: str | Path | Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Load and validate a configuration.

    ``source`` is a mapping, a path to a YAML/JSON file, an inline JSON object string (what the
    workflow's rules pass), or None for all defaults. A file's errors name the file.
    """
    if source is None or isinstance(source, Mapping):
        return validate(source)
    text = str(source)
    if text.lstrip().startswith("{"):
        try:
            return validate(json.loads(text, object_pairs_hook=_unique_pairs))
        except json.JSONDecodeError as exc:
            raise ConfigError(f"inline configuration is not valid JSON: {exc}") from exc
    doc = read_yaml(text)
    try:
        return validate(doc or {})
    except ConfigError as exc:
        raise ConfigError(f"configuration file {text}: {exc}") from None


def check_value(field: Iterable[str | int], value: Any, what: str | None = None) -> None:
    """Refuse ``value`` where it breaks the schema of the field at ``field`` (keys and list
    positions, e.g. ``("sweep", "speeds", 0)``), the one source of every bound: a command-line
    flag such as ``--speed`` takes what the config's field takes. ``what`` names the value in
    the message, if given."""
    field = tuple(field)
    sub = schema()
    for part in field:
        sub = sub["items"] if isinstance(part, int) else sub["properties"][part]
    for e in _Validator(sub).iter_errors(value):
        named = field_name(part for part in field if not isinstance(part, int))
        prefix = f"{what}: " if what else ""
        raise ConfigError(f"{prefix}{e.message} ({_allowed(e)}, as for config field '{named}')")
