"""Config dataclasses to and from TOML and plain dicts, with an exact round trip.

Every command's settings are a frozen dataclass (``VpSlamConfig``, ``RegistrationConfig``,
``CorridorConfig``, ...). ``octofactor CMD --dump-config`` writes one as TOML and
``--config FILE`` reads it back: ``config_from_toml(cls, config_to_toml(c)) == c`` for every
config whose values are bools, ints, floats (inf/nan included), strings, tuples of those,
``None`` or nested config dataclasses. JSON (report.json) round-trips the same way through
:func:`config_from_dict`, and the dataclasses call :func:`coerce_fields` in ``__post_init__``
so that ``VpSlamConfig(**report["config"]) == config`` as well (nested dicts become the nested
dataclasses, lists become tuples).

TOML is read with the standard library (``tomllib``, Python 3.11; on 3.10 the API-identical
``tomli`` if present) and written here: the subset needed is small (scalars, arrays of
scalars, one table per nested dataclass) and a writer dependency is not worth it. ``None``
has no TOML spelling: a ``None`` that is the field's default is written as a comment (a missing
key reads back as the default); any other ``None`` is written as the string ``"none"``, which
reads back as ``None`` in fields whose annotation allows ``None`` (and stays a string in the
others, e.g. ``vp_model = "none"``).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
from typing import Any

from estimation.errors import FormatError, OctofactorError


def _default_of(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _is_tuple_field(f: dataclasses.Field, default: Any) -> bool:
    return isinstance(default, tuple) or "tuple" in str(f.type)


def _to_tuple(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return tuple(_to_tuple(v) for v in value)
    return value


def coerce_fields(obj) -> None:
    """In a frozen dataclass's ``__post_init__``: nested config dicts -> dataclasses, lists ->
    tuples, so that ``Cls(**asdict(c)) == c`` and ``Cls(**json.loads(...)) == c``."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        default = _default_of(f)
        if isinstance(value, dict) and dataclasses.is_dataclass(default):
            object.__setattr__(obj, f.name, config_from_dict(type(default), value,
                                                             where=f.name))
        elif isinstance(value, list) and _is_tuple_field(f, default):
            object.__setattr__(obj, f.name, _to_tuple(value))


def config_from_dict(cls, data: dict, where: str = "config"):
    """``cls`` built from a (nested) dict; unknown keys raise an OctofactorError naming them."""
    if not isinstance(data, dict):
        raise OctofactorError(f"{where}: expected a table of settings, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise OctofactorError(f"{where}: unknown setting(s) {', '.join(unknown)} for "
                              f"{cls.__name__} (known: {', '.join(fields)})")
    kwargs = {}
    for name, value in data.items():
        f = fields[name]
        default = _default_of(f)
        if isinstance(value, dict) and dataclasses.is_dataclass(default):
            value = config_from_dict(type(default), value, where=f"{where}.{name}")
        elif isinstance(value, list):
            value = _to_tuple(value)
        elif value == "none" and "None" in str(f.type):
            value = None
        elif isinstance(default, float) and isinstance(value, int) \
                and not isinstance(value, bool):
            value = float(value)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise OctofactorError(f"{where}: {exc}") from None


def _toml_scalar(value: Any, where: str) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        text = repr(value)  # shortest repr: reads back to the same double
        return text if any(c in text for c in ".en") else text + ".0"
    if isinstance(value, str):
        return json.dumps(value)  # JSON's escapes are valid in TOML basic strings
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml_scalar(v, where) for v in value) + "]"
    raise OctofactorError(f"{where}: cannot write {type(value).__name__} {value!r} to TOML")


def config_to_toml(config, header: str | None = None) -> str:
    """TOML text of a config dataclass (nested dataclasses as tables)."""
    lines = [f"# {line}" for line in (header or "").splitlines()]
    tables = []

    def emit(obj, prefix: str, out: list[str]) -> None:
        for f in dataclasses.fields(obj):
            if not f.init:
                continue
            value = getattr(obj, f.name)
            key = f"{prefix}{f.name}"
            if dataclasses.is_dataclass(value):
                tables.append((key, value))
            elif value is None:
                out.append(f"# {f.name} = (none)" if _default_of(f) is None
                           else f'{f.name} = "none"')
            else:
                out.append(f"{f.name} = {_toml_scalar(value, key)}")

    emit(config, "", lines)
    while tables:
        key, value = tables.pop(0)
        lines += ["", f"[{key}]"]
        emit(value, f"{key}.", lines)
    return "\n".join(lines) + "\n"


def read_toml(path: str | os.PathLike) -> dict:
    """The table of a TOML file; a syntax error names the file and the position."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        try:
            import tomli as tomllib
        except ModuleNotFoundError:
            raise OctofactorError("--config needs Python 3.11 (tomllib) or the tomli "
                                  "package") from None
    with open(path, "rb") as handle:
        try:
            return tomllib.load(handle)
        except tomllib.TOMLDecodeError as exc:
            raise FormatError(path, str(exc)) from None
        except UnicodeDecodeError:
            raise FormatError(path, "not UTF-8 text") from None


def config_from_toml(cls, path: str | os.PathLike):
    """``cls`` from a TOML file written by :func:`config_to_toml` (or by hand)."""
    return config_from_dict(cls, read_toml(path), where=str(path))
