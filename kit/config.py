"""Config loading: frozen dataclasses per stage, from TOML plus `--set a.b=c` overrides.

Unknown keys and values of the wrong type raise ConfigError naming the key; nothing is swallowed.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
import types
import typing
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from octolog.kit.errors import ConfigError

if TYPE_CHECKING:  # typeshed's protocol of a dataclass instance: no run-time name
    from _typeshed import DataclassInstance

T = TypeVar("T")


def _coerce(value: Any, tp: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key)
            except ConfigError:
                continue
        raise ConfigError(f"config key {key!r}: {value!r} is not a valid {tp}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"config key {key!r}: want a table, got {value!r}")
        return from_dict(tp, value, prefix=f"{key}.")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key {key!r}: want a list, got {value!r}")
        (item_tp, *_rest) = typing.get_args(tp) or (Any,)
        return tuple(_coerce(v, item_tp, key) for v in value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"config key {key!r}: want true or false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"config key {key!r}: want an integer, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise ConfigError(f"config key {key!r}: want a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"config key {key!r}: want a string, got {value!r}")
    if tp is Any:
        return value
    raise ConfigError(f"config key {key!r}: unsupported type {tp}")


def from_dict(cls: type[T], data: dict[str, Any], *, prefix: str = "") -> T:
    """Build dataclass `cls` from a nested dict, validating every key and value."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    renamed = getattr(cls, "RENAMED", {})  # old key -> its name now: say so instead of "unknown"
    for key in unknown:
        if key in renamed:
            raise ConfigError(f"config key {prefix}{key!r} is now {prefix}{renamed[key]!r}")
    if unknown:
        raise ConfigError(f"unknown config key {prefix}{unknown[0]!r} (known: {', '.join(sorted(fields))})")
    kwargs = {name: _coerce(value, hints[name], prefix + name) for name, value in data.items()}
    obj = cls(**kwargs)
    check = getattr(obj, "validate", None)
    if check is not None:
        check()
    return obj


def _parse_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text  # bare strings need no quotes on the command line


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply `a.b=c` overrides (values parsed as TOML, else taken as strings)."""
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: want key=value")
        key, text = item.split("=", 1)
        node = data
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {part!r} is not a table")
        node[parts[-1]] = _parse_value(text.strip())
    return data


# the sections of a session's config file (config.toml): one per stage
SECTIONS = ("replay", "tracker", "mapper", "recorder")


def _for_section(cls: type, overrides: list[str], section: str) -> list[str]:
    """`--set` overrides for one [section]: `KEY=V` as it is, `SECTION.KEY=V` (the form `octolog run`
    takes) with the section dropped; another section's key is an error saying which form fits."""
    fields = {f.name for f in dataclasses.fields(cls)}
    out = []
    for item in overrides:
        head, dot, _ = item.split("=", 1)[0].strip().partition(".")
        if dot and head in SECTIONS and head not in fields:
            if head != section:
                raise ConfigError(f"--set {item!r}: this command takes [{section}] keys: --set KEY=VALUE "
                                  f"or --set {section}.KEY=VALUE")
            item = item.strip()[len(section) + 1:]
        out.append(item)
    return out


def load(cls: type[T], path: str | Path | None = None, overrides: list[str] | None = None,
         *, section: str | None = None, own: bool = False) -> T:
    """Load `cls` from an optional TOML file (optionally one [section] of it) and overrides (with a
    section: `KEY=V` or `SECTION.KEY=V` alike). `own`: the file is for this section's command alone,
    so one that holds other stages' sections and not this one is an error (the wrong file)."""
    if section is not None and overrides:
        overrides = _for_section(cls, overrides, section)
    data: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        try:
            data = tomllib.loads(p.read_text())
        except FileNotFoundError:
            raise ConfigError(f"{p}: config file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}: invalid TOML: {exc}") from None
        except UnicodeDecodeError as exc:  # found by tests/kit/test_fuzz.py
            raise ConfigError(f"{p}: not a TOML text file (byte {exc.start} is not UTF-8)") from None
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read the config file: {exc.strerror}") from None
        if section is not None:
            others = sorted(k for k in data if k in SECTIONS and k != section)
            if own and section not in data and others:
                raise ConfigError(f"{p}: no [{section}] section (it has {', '.join(f'[{k}]' for k in others)}); "
                                  f"this command reads [{section}]")
            data = data.get(section, {})
    return from_dict(cls, apply_overrides(data, overrides or []))


def to_dict(obj: DataclassInstance) -> dict[str, Any]:
    return dataclasses.asdict(obj)


def to_json(obj: DataclassInstance) -> str:
    """Canonical JSON of a resolved config (sorted keys), as stored in MCAP metadata."""
    return json.dumps(to_dict(obj), sort_keys=True)


def _toml_value(v: object, key: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x, key) for x in v) + "]"
    raise ConfigError(f"config key {key!r}: cannot write {v!r} to TOML")


def to_toml(tables: dict[str, dict[str, object]]) -> str:
    """TOML text of resolved configs ({section: to_dict(cfg)}), nested dataclasses as sub-tables;
    `load(cls, path, section=...)` reads it back. None values are left out (they are defaults)."""
    out: list[str] = []

    def table(name: str, items: dict[str, object]) -> None:
        out.append(f"[{name}]")
        out.extend(f"{k} = {_toml_value(v, f'{name}.{k}')}" for k, v in items.items()
                   if v is not None and not isinstance(v, dict))
        out.append("")
        for k, v in items.items():
            if isinstance(v, dict):
                table(f"{name}.{k}", v)

    for name, items in tables.items():
        table(name, items)
    return "\n".join(out)
