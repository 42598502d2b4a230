"""Config dataclasses as the one source of defaults, types and ranges.

A field declared with ``bounded(default, ge=..., le=..., choices=...)`` carries
its range in its metadata; ``check_fields`` checks every field of a config
section against its annotation (an int is fine for a float, a bool is not an
int; floats must be finite) and that range, naming the field in one line.
``from_mapping`` builds a section from JSON-like data (a partial map is a set
of overrides on the defaults; lists become tuples, maps nested sections) and
``parse_value`` turns a command-line string into a field's type. So a config
file, a ``--set KEY=VALUE`` and a flag reach the code one way, and each
section's ranges sit beside its defaults.

Written here rather than taken from a CLI library (tyro, as CleanRL uses):
``sage train --config FILE --seed 3`` must apply *only* the flags the user
typed over a loaded file, and every numeric field needs a physical or resource
range, which such libraries leave to the caller anyway.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import types
import typing

_UNSET = object()


def bounded(default=_UNSET, *, ge=None, gt=None, le=None, lt=None, choices=None, default_factory=_UNSET,
            help: str = ""):
    """A dataclass field with a range (``ge``/``gt``/``le``/``lt``) or a set of ``choices``."""
    meta = {"range": (ge, gt, le, lt), "choices": tuple(choices) if choices is not None else None, "help": help}
    if default_factory is not _UNSET:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def field_help(f: dataclasses.Field) -> str:
    return f.metadata.get("help", "") if f.metadata else ""


@functools.lru_cache(maxsize=None)
def type_hints(cls) -> dict:
    """``typing.get_type_hints(cls)``, once per class: it compiles every annotation
    string anew on each call (82% of a ``sage suite --dry-run`` of 300 configs)."""
    return typing.get_type_hints(cls)


def _describe_range(ge, gt, le, lt) -> str:
    parts = []
    if ge is not None:
        parts.append(f">= {ge}")
    if gt is not None:
        parts.append(f"> {gt}")
    if le is not None:
        parts.append(f"<= {le}")
    if lt is not None:
        parts.append(f"< {lt}")
    return " and ".join(parts)


def coerce(value, hint, path: str):
    """``value`` as type ``hint`` (int, float, bool, str, X | None, tuple[...], list[str],
    a nested dataclass given as a map); a ``ValueError`` naming ``path`` otherwise."""
    origin, targs = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in targs:
            return None
        inner = [t for t in targs if t is not type(None)]
        errors = []
        for t in inner:
            try:
                return coerce(value, t, path)
            except ValueError as exc:
                errors.append(str(exc).split(" must be ", 1)[-1].rsplit(", got ", 1)[0])
        wanted = " or ".join(errors + (["null"] if type(None) in targs else []))
        raise ValueError(f"{path} must be {wanted}, got {value!r}")
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise ValueError(f"{path} must be true or false, got {value!r}")
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ValueError(f"{path} must be an integer, got {value!r}")
    if hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):
                raise ValueError(f"{path} must be a finite number, got {value!r}")
            return float(value)
        raise ValueError(f"{path} must be a number, got {value!r}")
    if hint is str:
        if isinstance(value, str):
            return value
        raise ValueError(f"{path} must be a string, got {value!r}")
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{path} must be a list ({_hint_name(hint)}), got {value!r}")
        if origin is tuple and targs and targs[-1] is not Ellipsis:
            if len(value) != len(targs):
                raise ValueError(f"{path} must be a list of {len(targs)} ({_hint_name(hint)}), got {value!r}")
            items = [coerce(v, t, f"{path}[{i}]") for i, (v, t) in enumerate(zip(value, targs))]
        else:
            t = targs[0] if targs else typing.Any
            items = [v if t is typing.Any else coerce(v, t, f"{path}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else list(items)
    if dataclasses.is_dataclass(hint):
        if isinstance(value, hint):
            return value
        if isinstance(value, dict):
            return from_mapping(hint, value, path + ".")
        raise ValueError(f"{path} must be a map of {hint.__name__} fields, got {value!r}")
    return value


def _hint_name(hint) -> str:
    return str(hint).replace("typing.", "")


def from_mapping(cls, values: dict, prefix: str = "", base=None):
    """``cls`` built from a JSON-like map: every key coerced to its field's type,
    unknown keys refused; fields the map leaves out keep ``base``'s values (the
    defaults when ``base`` is None). The instance's own checks run on construction."""
    if not isinstance(values, dict):
        raise ValueError(f"{prefix.rstrip('.') or cls.__name__} must be a map of {cls.__name__} fields, "
                         f"got {values!r}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"unknown {prefix.rstrip('.') + ' ' if prefix else ''}config keys {unknown} "
                         f"({cls.__name__} has {', '.join(sorted(names))})")
    hints = type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        if f.name in values:
            out[f.name] = coerce(values[f.name], hints[f.name], prefix + f.name)
        elif base is not None:
            out[f.name] = getattr(base, f.name)
    return cls(**out)


def check_fields(obj, prefix: str = "") -> None:
    """Every field of the dataclass ``obj`` has its annotated type, a finite value where
    it is a number, and lies in its declared range or choices; nested sections are
    checked in turn. A ``ValueError`` naming the first field that does not."""
    hints = type_hints(type(obj))
    for f in dataclasses.fields(obj):
        path = prefix + f.name
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            check_fields(value, path + ".")
            continue
        checked = coerce(value, hints[f.name], path)
        if checked is not value and isinstance(checked, float) and type(value) is int:
            object.__setattr__(obj, f.name, checked)   # an int given for a float field
        check_range(f, value, path)


def check_range(f: dataclasses.Field, value, path: str) -> None:
    """``value`` of field ``f`` lies in its declared range or choices (None passes:
    where None is allowed the annotation says so)."""
    if not f.metadata or value is None:
        return
    choices = f.metadata.get("choices")
    if choices is not None and value not in choices:
        raise ValueError(f"{path} must be one of {', '.join(map(str, choices))}, got {value!r}")
    ge, gt, le, lt = f.metadata.get("range", (None,) * 4)
    items = value if isinstance(value, (tuple, list)) else (value,)
    for v in items:
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            ok = (ge is None or v >= ge) and (gt is None or v > gt) and (le is None or v <= le) \
                and (lt is None or v < lt)
            if not ok:
                raise ValueError(f"{path} must be {_describe_range(ge, gt, le, lt)}, got {value!r}")


def parse_value(raw: str, hint, path: str):
    """A command-line string as the field's type: JSON first (``1e-3``, ``true``,
    ``null``, ``[0.05, 1]``), else the text itself for a string field."""
    try:
        value = json.loads(raw)
    except (json.JSONDecodeError, RecursionError):
        value = raw
    if not isinstance(value, str) and _accepts_str(hint) and not _accepts(value, hint):
        value = raw   # e.g. run_id=123 stays the string "123"
    return coerce(value, hint, path)


def _accepts_str(hint) -> bool:
    return hint is str or (typing.get_origin(hint) in (typing.Union, types.UnionType) and str in typing.get_args(hint))


def _accepts(value, hint) -> bool:
    try:
        coerce(value, hint, "")
        return True
    except ValueError:
        return False


def loads_json(text: str):
    """``json.loads`` whose too-deeply-nested input is a ``ValueError``, not a ``RecursionError``;
    NaN and Infinity are refused (no config value is meant to be one)."""
    def no_constant(name):
        raise ValueError(f"{name} is not a valid config value")
    try:
        return json.loads(text, parse_constant=no_constant)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None
