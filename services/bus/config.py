"""Typed, validated service configuration: TOML file < environment variables < CLI flags.

Every service describes its configuration as a dataclass deriving from :class:`ServiceConfig`
(which brings the bus settings: ``prefix``, ``[zenoh]``, logging, status period) and adds its own
sections as nested dataclasses. :func:`load_config` builds it from defaults, an optional TOML file
(stdlib ``tomllib``), environment variables and CLI overrides, and validates every field by its
type annotation and ``field(metadata=...)`` constraints at start-up. A bad value raises
:class:`ConfigError` whose message is one line naming the field::

    config error: zenoh.mode: expected one of peer|client|router, got 'x'

Environment variables: every field ``a.b`` is read from ``PSM_A_B`` (upper case), e.g.
``PSM_PREFIX``, ``PSM_ZENOH_MODE``, ``PSM_ZENOH_CONNECT`` (comma-separated list),
``PSM_ZENOH_LISTEN``, ``PSM_ARM_DT_S``; aliases: ``PSM_MULTICAST`` = ``zenoh.multicast``.

Example (a service's own config)::

    from dataclasses import dataclass, field
    from services.bus.config import ServiceConfig, add_config_arguments, config_from_args, spec

    @dataclass
    class ArmSection:
        dt_s: float = spec(0.002, "control period, s", gt=0.0, le=0.1)
        clock: str = spec("realtime", "clock mode", choices=("realtime", "lockstep"))

    @dataclass
    class ArmConfig(ServiceConfig):
        arm: ArmSection = field(default_factory=ArmSection)

    # in register(): add_config_arguments(parser)
    # in func(args): cfg = config_from_args(ArmConfig, args)   # raises ConfigError

TOML file::

    prefix = "psm"
    [zenoh]
    mode = "client"
    connect = ["tcp/127.0.0.1:7447"]
    multicast = false
    [arm]
    dt_s = 0.001
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tomllib
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

__all__ = [
    "ENV_ALIASES",
    "ConfigError",
    "ServiceConfig",
    "ZenohConfig",
    "add_config_arguments",
    "config_from_args",
    "config_to_dict",
    "env_var_name",
    "load_config",
    "meta",
    "spec",
]

T = TypeVar("T")

#: Environment variables that are not the generic ``PSM_<SECTION>_<FIELD>`` name of a field.
ENV_ALIASES: dict[str, str] = {"PSM_MULTICAST": "zenoh.multicast"}
ENV_PREFIX = "PSM_"


class ConfigError(ValueError):
    """An invalid configuration; ``str(err)`` is one line: ``config error: <field>: <why>``."""

    def __init__(self, path: str, reason: str) -> None:
        self.path = path
        self.reason = reason
        super().__init__(f"config error: {path}: {reason}" if path else f"config error: {reason}")


def meta(
    help: str = "",
    *,
    choices: Sequence[Any] | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    min_len: int | None = None,
) -> dict[str, Any]:
    """Field metadata understood by the validator (see :func:`spec`)."""
    return {
        "help": help,
        "choices": tuple(choices) if choices is not None else None,
        "ge": ge,
        "gt": gt,
        "le": le,
        "lt": lt,
        "min_len": min_len,
    }


def spec(
    default: Any = dataclasses.MISSING,
    help: str = "",
    *,
    choices: Sequence[Any] | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    min_len: int | None = None,
    default_factory: Any = dataclasses.MISSING,
) -> Any:
    """A dataclass ``field`` with a help text and validation constraints (``choices``, numeric
    bounds ``ge``/``gt``/``le``/``lt``, ``min_len`` for strings and lists).

    For list fields ruff prefers ``field(default_factory=list, metadata=meta(...))``.
    """
    metadata = meta(help, choices=choices, ge=ge, gt=gt, le=le, lt=lt, min_len=min_len)
    if default_factory is not dataclasses.MISSING:
        return field(default_factory=default_factory, metadata=metadata)
    if isinstance(default, list | dict):
        value = default
        return field(default_factory=lambda: type(value)(value), metadata=metadata)
    return field(default=default, metadata=metadata)


# --------------------------------------------------------------------------------------------
# The bus sections every service has
# --------------------------------------------------------------------------------------------


@dataclass
class ZenohConfig:
    """How a service joins the Zenoh network."""

    mode: str = spec("peer", "zenoh mode", choices=("peer", "client", "router"))
    connect: list[str] = field(
        default_factory=list, metadata=meta("endpoints to connect to, e.g. tcp/127.0.0.1:7447")
    )
    listen: list[str] = field(
        default_factory=list, metadata=meta("endpoints to listen on, e.g. tcp/0.0.0.0:7447")
    )
    multicast: bool = spec(True, "multicast scouting on/off (docker and tests: off)")
    gossip: bool = spec(True, "gossip scouting on/off")
    config_file: str = spec("", "optional zenoh JSON5 config file applied first")
    shared_memory: bool = spec(False, "enable zenoh shared-memory transport")
    low_latency: bool = spec(
        False,
        "zenoh's low-latency unicast transport (no batching pipeline, QoS priorities off); used "
        "on a link only if both ends enable it. For the arm<->planner control loop (see "
        "docs/bus.md for what it measured here). Not for sessions that send messages near or "
        "above 64 KiB (camera images): the low-latency transport does not fragment and was "
        "measured to drop some of them",
    )

    def validate(self) -> None:
        """Cross-field checks (called by the loader)."""
        for name in ("connect", "listen"):
            for ep in getattr(self, name):
                proto, sep, rest = ep.partition("/")
                if not sep or not proto or not rest:
                    raise ConfigError(
                        f"zenoh.{name}", f"expected endpoints like 'tcp/HOST:PORT', got {ep!r}"
                    )
        if self.mode == "client" and not self.connect and not self.multicast:
            raise ConfigError(
                "zenoh.connect", "client mode with multicast off needs at least one endpoint"
            )


@dataclass
class ServiceConfig:
    """Settings shared by every service; services subclass it and add sections."""

    prefix: str = spec("psm", "key-expression prefix of the cell", min_len=1)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    log_level: str = spec(
        "INFO", "log level", choices=("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
    )
    log_format: str = spec("text", "log line format", choices=("text", "json"))
    status_period_s: float = spec(1.0, "ServiceStatus publication period, s", gt=0.0, le=3600.0)
    queue_size: int = spec(
        1024, "default bounded queue length of subscription handlers", ge=1, le=10_000_000
    )

    def validate(self) -> None:
        """Cross-field checks (called by the loader)."""
        from services.bus.messages import InvalidKeyError, Keys

        try:
            Keys(self.prefix)
        except InvalidKeyError as exc:
            raise ConfigError("prefix", str(exc)) from None


# --------------------------------------------------------------------------------------------
# Loading and validation
# --------------------------------------------------------------------------------------------


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _fields(cls: type) -> list[dataclasses.Field[Any]]:
    return [f for f in dataclasses.fields(cls) if f.init]


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _parse_bool(path: str, value: Any) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str):
        low = value.strip().lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
    raise ConfigError(path, f"expected a boolean (true/false), got {value!r}")


def _coerce(path: str, tp: Any, value: Any, from_text: bool) -> Any:
    """Convert ``value`` to annotation ``tp`` (parsing strings when ``from_text``)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if type(None) in args and (value is None or (from_text and value == "")):
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(path, arg, value, from_text)
            except ConfigError as exc:
                errors.append(exc.reason)
        raise ConfigError(path, errors[0] if errors else f"invalid value {value!r}")
    if origin is Literal:
        choices = args
        if from_text and isinstance(value, str):
            for c in choices:
                if str(c) == value:
                    return c
        if value not in choices:
            raise ConfigError(
                path, f"expected one of {'|'.join(map(str, choices))}, got {value!r}"
            )
        return value
    if origin in (list, tuple, Sequence):
        item_tp = args[0] if args else Any
        if from_text and isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, list | tuple):
            raise ConfigError(path, f"expected a list, got {value!r}")
        items = [_coerce(f"{path}[{i}]", item_tp, v, from_text) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is Any:
        return value
    if tp is bool:
        return _parse_bool(path, value)
    if tp is int:
        if isinstance(value, bool):
            raise ConfigError(path, f"expected an integer, got {value!r}")
        if isinstance(value, int):
            return value
        if from_text and isinstance(value, str):
            try:
                return int(value.strip(), 0)
            except ValueError:
                pass
        raise ConfigError(path, f"expected an integer, got {value!r}")
    if tp is float:
        if isinstance(value, bool):
            raise ConfigError(path, f"expected a number, got {value!r}")
        if isinstance(value, int | float):
            return float(value)
        if from_text and isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                pass
        raise ConfigError(path, f"expected a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(path, f"expected a string, got {value!r}")
    if tp is Path:
        if isinstance(value, str | Path):
            return Path(value)
        raise ConfigError(path, f"expected a path, got {value!r}")
    raise ConfigError(path, f"unsupported field type {_type_name(tp)}")


def _check_constraints(path: str, f: dataclasses.Field[Any], value: Any) -> None:
    md = f.metadata
    choices = md.get("choices")
    if choices and value not in choices:
        raise ConfigError(path, f"expected one of {'|'.join(map(str, choices))}, got {value!r}")
    for key, ok, word in (
        ("ge", lambda v, b: v >= b, ">="),
        ("gt", lambda v, b: v > b, ">"),
        ("le", lambda v, b: v <= b, "<="),
        ("lt", lambda v, b: v < b, "<"),
    ):
        bound = md.get(key)
        if bound is not None and isinstance(value, int | float) and not ok(value, bound):
            raise ConfigError(path, f"expected a value {word} {bound}, got {value!r}")
    if isinstance(value, float) and value != value:  # NaN
        raise ConfigError(path, "expected a number, got nan")
    min_len = md.get("min_len")
    if min_len is not None and hasattr(value, "__len__") and len(value) < min_len:
        raise ConfigError(path, f"expected at least {min_len} item(s)/character(s), got {value!r}")


def _build(cls: type[T], data: Mapping[str, Any], path: str, from_text: bool) -> T:
    """Build dataclass ``cls`` from nested ``data`` (missing fields keep their defaults)."""
    if not isinstance(data, Mapping):
        raise ConfigError(path, f"expected a table, got {data!r}")
    hints = _hints(cls)
    known = {f.name: f for f in _fields(cls)}
    for key in data:
        if key not in known:
            where = f"{path}.{key}" if path else key
            raise ConfigError(where, f"unknown field (known: {', '.join(sorted(known))})")
    kwargs: dict[str, Any] = {}
    for name in known:
        sub = f"{path}.{name}" if path else name
        tp = hints[name]
        if _is_dataclass_type(tp):
            kwargs[name] = _build(tp, data.get(name, {}), sub, from_text)
            continue
        if name not in data:
            continue
        value = _coerce(sub, tp, data[name], from_text)
        kwargs[name] = value
    obj = cls(**kwargs)
    _validate(obj, path)
    return obj


def _validate(obj: Any, path: str) -> None:
    hints = _hints(type(obj))
    for f in _fields(type(obj)):
        sub = f"{path}.{f.name}" if path else f.name
        value = getattr(obj, f.name)
        if _is_dataclass_type(hints[f.name]):
            continue  # validated when built
        _check_constraints(sub, f, value)
    validate = getattr(obj, "validate", None)
    if callable(validate):
        try:
            validate()
        except ConfigError as exc:
            if path and not exc.path.startswith(path + "."):
                raise ConfigError(f"{path}.{exc.path}", exc.reason) from None
            raise


def _leaf_paths(cls: type, prefix: str = "") -> dict[str, Any]:
    """Every leaf field of ``cls`` as ``dotted.path -> annotation``."""
    out: dict[str, Any] = {}
    hints = _hints(cls)
    for f in _fields(cls):
        path = f"{prefix}.{f.name}" if prefix else f.name
        tp = hints[f.name]
        if _is_dataclass_type(tp):
            out.update(_leaf_paths(tp, path))
        else:
            out[path] = tp
    return out


def env_var_name(path: str) -> str:
    """Environment variable of a dotted field path: ``zenoh.mode`` -> ``PSM_ZENOH_MODE``."""
    return ENV_PREFIX + path.replace(".", "_").upper()


def _set_path(tree: dict[str, Any], path: str, value: Any) -> None:
    parts = path.split(".")
    node = tree
    for p in parts[:-1]:
        nxt = node.setdefault(p, {})
        if not isinstance(nxt, dict):
            raise ConfigError(path, f"{p} is not a table")
        node = nxt
    node[parts[-1]] = value


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def _text_to_typed(path: str, tp: Any, text: str) -> Any:
    return _coerce(path, tp, text, from_text=True)


def load_config(
    cls: type[T],
    path: str | Path | None = None,
    *,
    overrides: Mapping[str, Any] | None = None,
    env: Mapping[str, str] | None = None,
) -> T:
    """Build and validate a ``cls`` config.

    Precedence, lowest first: dataclass defaults, the TOML file at ``path`` (if given), the
    environment ``env`` (default ``os.environ``; ``PSM_<SECTION>_<FIELD>`` and
    :data:`ENV_ALIASES`), then ``overrides`` (dotted path -> value; strings are parsed like env
    values, e.g. from ``--set arm.dt_s=0.001``). Raises :class:`ConfigError`.
    """
    if not _is_dataclass_type(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    env = os.environ if env is None else env
    data: dict[str, Any] = {}
    if path is not None and str(path) != "":
        p = Path(path)
        try:
            with p.open("rb") as fh:
                data = tomllib.load(fh)
        except FileNotFoundError:
            raise ConfigError("", f"config file not found: {p}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("", f"{p}: invalid TOML: {exc}") from None
        except OSError as exc:
            raise ConfigError("", f"cannot read config file {p}: {exc.strerror}") from None
        # type-check the file's values strictly (no string parsing) before layering
        _build(cls, data, "", from_text=False)
    leaves = _leaf_paths(cls)
    layered: dict[str, Any] = {}
    env_map = {env_var_name(p): p for p in leaves}
    env_map.update({k: v for k, v in ENV_ALIASES.items() if v in leaves})
    for var, fpath in env_map.items():
        if var in env:
            try:
                _set_path(layered, fpath, _text_to_typed(fpath, leaves[fpath], env[var]))
            except ConfigError as exc:
                raise ConfigError(f"{exc.path} (from ${var})", exc.reason) from None
    for fpath, value in (overrides or {}).items():
        if value is None:
            continue
        if fpath not in leaves:
            raise ConfigError(fpath, "unknown field")
        if isinstance(value, str):
            value = _text_to_typed(fpath, leaves[fpath], value)
        _set_path(layered, fpath, value)
    return _build(cls, _merge(data, layered), "", from_text=False)


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """A plain nested dict of a config (for metadata snapshots and ``--print-config``)."""

    def conv(v: Any) -> Any:
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, list | tuple):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        return v

    return conv(dataclasses.asdict(cfg))


# --------------------------------------------------------------------------------------------
# Command-line integration
# --------------------------------------------------------------------------------------------


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the common bus flags: ``--config``, ``--prefix``, ``--mode``, ``--connect``,
    ``--listen``, ``--multicast/--no-multicast``, ``--low-latency``, ``--log-level``,
    ``--set PATH=VALUE``."""
    g = parser.add_argument_group("bus configuration (flags override env vars override file)")
    g.add_argument("--config", metavar="FILE.toml", help="TOML config file")
    g.add_argument("--prefix", help="key-expression prefix (env PSM_PREFIX, default psm)")
    g.add_argument("--mode", choices=("peer", "client", "router"), help="zenoh mode")
    g.add_argument(
        "--connect", action="append", metavar="ENDPOINT", help="zenoh endpoint to connect to "
        "(repeatable, e.g. tcp/127.0.0.1:7447)"
    )
    g.add_argument(
        "--listen", action="append", metavar="ENDPOINT", help="zenoh endpoint to listen on"
    )
    g.add_argument(
        "--multicast", action=argparse.BooleanOptionalAction, default=None,
        help="multicast scouting on/off",
    )
    g.add_argument(
        "--low-latency", action=argparse.BooleanOptionalAction, default=None,
        help="zenoh low-latency transport (control loops; see zenoh.low_latency)",
    )
    g.add_argument("--log-level", help="DEBUG|INFO|WARNING|ERROR")
    g.add_argument(
        "--set", action="append", default=[], metavar="PATH=VALUE",
        help="override any config field, e.g. --set arm.dt_s=0.001",
    )


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The config overrides given by :func:`add_config_arguments` flags."""
    out: dict[str, Any] = {
        "prefix": getattr(args, "prefix", None),
        "zenoh.mode": getattr(args, "mode", None),
        "zenoh.connect": getattr(args, "connect", None),
        "zenoh.listen": getattr(args, "listen", None),
        "zenoh.multicast": getattr(args, "multicast", None),
        "zenoh.low_latency": getattr(args, "low_latency", None),
        "log_level": getattr(args, "log_level", None),
    }
    for item in getattr(args, "set", None) or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError("", f"--set expects PATH=VALUE, got {item!r}")
        out[key.strip()] = value
    return {k: v for k, v in out.items() if v is not None}


def config_from_args(
    cls: type[T],
    args: argparse.Namespace,
    extra: Mapping[str, Any] | None = None,
    env: Mapping[str, str] | None = None,
) -> T:
    """Load ``cls`` from ``args.config`` + env + the flags of :func:`add_config_arguments`
    (+ ``extra`` overrides a command maps from its own flags)."""
    overrides = overrides_from_args(args)
    overrides.update({k: v for k, v in (extra or {}).items() if v is not None})
    return load_config(cls, getattr(args, "config", None), overrides=overrides, env=env)
