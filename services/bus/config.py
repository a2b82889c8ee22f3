"""Typed, validated service configuration: TOML file < environment variables < CLI flags.

Every service describes its configuration as a subclass of :class:`ServiceConfig` (the bus
settings every process shares: ``prefix``, ``clock``, ``[zenoh]``, logging, status period) with
its own sections as nested :class:`Section` models (pydantic v2). :func:`load_config` builds it
with pydantic-settings from the model defaults, a TOML file, the environment and overrides, and
validates every field at start-up. A bad value raises :class:`ConfigError` whose message is one
line naming the field::

    config error: zenoh.mode: Input should be 'peer', 'client' or 'router' (got 'x')

One file describes a whole stack (``configs/stack.toml``): each service reads the shared
top-level keys and its own sections and ignores the tables of the other services; a scalar it
does not know, or an unknown key inside its own sections, is an error.

Environment variables: ``PSM_<FIELD>`` for a top-level field, ``PSM_<SECTION>__<FIELD>`` for a
nested one (double underscore between levels), case-insensitive: ``PSM_PREFIX``,
``PSM_CLOCK``, ``PSM_ZENOH__MODE``, ``PSM_ZENOH__CONNECT`` (a comma-separated list or a JSON
list), ``PSM_ARM__DT_S``, ``PSM_GOAL_TRACKER__CAMERA__SOURCE``.

Example (a service's own config)::

    from pydantic import Field
    from services.bus.config import Section, ServiceConfig, load_config

    class ArmSection(Section):
        dt_s: float = Field(0.002, gt=0.0, le=0.1, description="control period [s]")

    class ArmConfig(ServiceConfig):
        arm: ArmSection = Field(default_factory=ArmSection)

    cfg = load_config(ArmConfig, "configs/stack.toml", overrides={"arm.dt_s": "0.001"})
"""

from __future__ import annotations

import argparse
import contextvars
import json
import math
import os
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_settings import (
    BaseSettings,
    EnvSettingsSource,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

__all__ = [
    "ENV_PREFIX",
    "ClockMode",
    "ConfigError",
    "EndpointList",
    "Section",
    "ServiceConfig",
    "StrList",
    "Vec3",
    "ZenohConfig",
    "add_config_arguments",
    "config_error",
    "config_from_args",
    "config_to_dict",
    "env_var_name",
    "load_config",
    "parse_override",
    "read_toml",
    "set_items",
]

T = TypeVar("T", bound="ServiceConfig")
S = TypeVar("S", bound="Section")

ENV_PREFIX = "PSM_"
ENV_NESTED_DELIMITER = "__"

#: The stack's clock: ``realtime`` (the arm sleeps to the wall clock) or ``lockstep`` (the arm
#: advances a tick only when the command answering the previous state has arrived).
ClockMode = Literal["realtime", "lockstep"]


class ConfigError(ValueError):
    """An invalid configuration; ``str(err)`` is one line: ``config error: <field>: <why>``."""

    def __init__(self, path: str, reason: str) -> None:
        self.path = path
        self.reason = reason
        super().__init__(f"config error: {path}: {reason}" if path else f"config error: {reason}")


def _split_commas(value: Any) -> Any:
    """A list given as text (environment, ``--set``) as ``a, b`` or a JSON list."""
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            try:
                return json.loads(text)
            except json.JSONDecodeError:
                return value
        return [v.strip() for v in text.split(",") if v.strip()]
    return value


#: A list of strings that may be given as comma-separated text.
StrList = Annotated[list[str], NoDecode, BeforeValidator(_split_commas)]
#: Zenoh endpoints (``tcp/HOST:PORT``), comma-separated in text.
EndpointList = StrList


def _check_vec3(value: Any) -> Any:
    if isinstance(value, list | tuple):
        if len(value) != 3:
            raise ValueError(f"expected 3 numbers, got {len(value)}")
        for v in value:
            if isinstance(v, int | float) and not math.isfinite(float(v)):
                raise ValueError(f"expected finite numbers, got {list(value)}")
    return value


#: A 3-vector of finite numbers (a list in TOML, JSON or comma-separated in text).
Vec3 = Annotated[list[float], NoDecode, BeforeValidator(_check_vec3), BeforeValidator(_split_commas)]


class Section(BaseModel):
    """A config section (a TOML table): unknown keys are errors, defaults are validated,
    assignments are validated too (``cfg.arm.dt_s = -1`` raises)."""

    model_config = ConfigDict(
        extra="forbid", validate_default=True, validate_assignment=True, allow_inf_nan=False
    )

    def check(self) -> None:
        """Cross-field checks of a section: raise :class:`ConfigError` with the field's name
        relative to the section (``ConfigError("upper_m", "must be > lower_m")``)."""

    def project(self, cls: type[S]) -> S:
        """This section's values of the fields of ``cls`` (a model this section extends), as a
        ``cls``: the parameter object a section feeds (``detector.project(PipelineParams)``)."""
        return cls(**{name: getattr(self, name) for name in cls.model_fields})

    @model_validator(mode="after")
    def _run_checks(self) -> Section:
        self.check()
        return self


# --------------------------------------------------------------------------------------------
# The bus sections every service has
# --------------------------------------------------------------------------------------------


class ZenohConfig(Section):
    """How a service joins the Zenoh network."""

    mode: Literal["peer", "client", "router"] = Field("peer", description="zenoh mode")
    connect: EndpointList = Field(
        default_factory=list, description="endpoints to connect to, e.g. tcp/127.0.0.1:7447"
    )
    listen: EndpointList = Field(
        default_factory=list, description="endpoints to listen on, e.g. tcp/0.0.0.0:7447"
    )
    multicast: bool = Field(True, description="multicast scouting on/off (docker and tests: off)")
    gossip: bool = Field(True, description="gossip scouting on/off")
    config_file: str = Field("", description="optional zenoh JSON5 config file applied first")
    shared_memory: bool = Field(False, description="enable zenoh shared-memory transport")
    reconnect_max_s: float = Field(
        0.5, gt=0.0, le=60.0,
        description="a lost router is retried every 0.1 s, doubling up to this period [s] (zenoh's "
        "connect/retry): a restarted router is rejoined within about this long",
    )
    low_latency: bool = Field(
        False,
        description="zenoh's low-latency unicast transport (no batching pipeline, QoS "
        "priorities off); used on a link only if both ends enable it. For the arm<->planner "
        "control loop. Not for sessions that send messages near or above 64 KiB (camera "
        "images): the low-latency transport does not fragment them",
    )
    user: str = Field(
        "",
        description="zenoh user/password authentication: the user this session authenticates "
        "as at the router ('' = no authentication); with access control on the router, the "
        "service's role (docs/security.md)",
    )
    password_file: str = Field(
        "", description="a file whose content (stripped) is the password of zenoh.user"
    )

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        for ep in value:
            proto, sep, rest = ep.partition("/")
            if not sep or not proto or not rest:
                raise ValueError(f"expected endpoints like 'tcp/HOST:PORT', got {ep!r}")
        return value

    def check(self) -> None:
        """A client without multicast scouting needs an endpoint; a user needs a readable,
        non-empty password file, and a password file a user."""
        if self.mode == "client" and not self.connect and not self.multicast:
            raise ConfigError("connect", "client mode with multicast off needs at least one endpoint")
        if self.user:
            self.password()
        elif self.password_file:
            raise ConfigError("user", f"is empty but password_file is set ({self.password_file})")

    def password(self) -> str:
        """The password of :attr:`user`: the stripped content of :attr:`password_file`
        (raises :class:`ConfigError` naming ``password_file`` if it cannot be read or is
        empty)."""
        if not self.password_file:
            raise ConfigError("password_file", f"is required with user {self.user!r}")
        try:
            text = Path(self.password_file).read_text(encoding="utf-8").strip()
        except OSError as exc:
            reason = exc.strerror.lower() if exc.strerror else type(exc).__name__
            raise ConfigError("password_file", f"cannot read {self.password_file}: {reason}") from None
        except UnicodeDecodeError:
            raise ConfigError("password_file", f"{self.password_file} is not UTF-8 text") from None
        if not text:
            raise ConfigError("password_file", f"{self.password_file} is empty")
        return text


class _Sources:
    """What :func:`load_config` layers under the init arguments (one load at a time per
    context): the parsed TOML file and the environment mapping."""

    def __init__(self, file_data: Mapping[str, Any], env: Mapping[str, str] | None) -> None:
        self.file_data = file_data
        self.env = env


_SOURCES: contextvars.ContextVar[_Sources | None] = contextvars.ContextVar(
    "psm_config_sources", default=None
)


class _MappingEnvSource(EnvSettingsSource):
    """pydantic-settings' environment source reading a given mapping instead of os.environ."""

    def __init__(self, settings_cls: type[BaseSettings], env: Mapping[str, str]) -> None:
        self._mapping = dict(env)
        super().__init__(settings_cls)

    def _load_env_vars(self) -> Mapping[str, str | None]:
        return {k.lower(): v for k, v in self._mapping.items()}


class _FileSource(PydanticBaseSettingsSource):
    """The TOML file of :func:`load_config`, with the tables of other services removed."""

    def __init__(self, settings_cls: type[BaseSettings], data: Mapping[str, Any]) -> None:
        super().__init__(settings_cls)
        self._data = {
            k: v for k, v in data.items()
            if k in settings_cls.model_fields or not isinstance(v, dict)
        }

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:
        return self._data.get(field_name), field_name, False

    def __call__(self) -> dict[str, Any]:
        return dict(self._data)


class ServiceConfig(BaseSettings):
    """Settings shared by every service; services subclass it and add sections."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_NESTED_DELIMITER,
        case_sensitive=False,
        extra="forbid",
        validate_default=True,
        validate_assignment=True,
        nested_model_default_partial_update=False,
    )

    prefix: str = Field("psm", min_length=1, description="key-expression prefix of the cell")
    clock: ClockMode = Field(
        "realtime",
        description="the stack's clock: realtime (the arm follows the wall clock) or lockstep "
        "(the arm steps when its command arrives: deterministic, faster than real time)",
    )
    zenoh: ZenohConfig = Field(default_factory=ZenohConfig)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"] = Field(
        "INFO", description="log level"
    )
    log_format: Literal["text", "json"] = Field("text", description="log line format")
    status_period_s: float = Field(
        1.0, gt=0.0, le=3600.0, description="ServiceStatus publication period [s]"
    )
    health_file: str = Field(
        "",
        description="'' or a file the service rewrites at every status period while it runs and "
        "(in client mode) is connected to a router: a container healthcheck tests its age",
    )
    queue_size: int = Field(
        1024, ge=1, le=10_000_000, description="bounded queue length of subscription handlers"
    )

    @field_validator("prefix")
    @classmethod
    def _prefix_is_a_key(cls, value: str) -> str:
        from services.bus.messages import InvalidKeyError, Keys

        try:
            Keys(value)
        except InvalidKeyError as exc:
            raise ValueError(str(exc)) from None
        return value

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        """Flags (init arguments) > environment > TOML file > defaults."""
        sources = _SOURCES.get()
        if sources is None:
            return (init_settings, env_settings)
        env: PydanticBaseSettingsSource = (
            env_settings if sources.env is None else _MappingEnvSource(settings_cls, sources.env)
        )
        return (init_settings, env, _FileSource(settings_cls, sources.file_data))


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------


def config_error(exc: ValidationError) -> ConfigError:
    """The first error of a pydantic ``ValidationError`` as one :class:`ConfigError` line."""
    err = exc.errors()[0]
    path = ""
    for part in err["loc"]:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    if err["type"] == "extra_forbidden":
        return ConfigError(path, "unknown field")
    if err["type"] == "missing":
        return ConfigError(path, "missing")
    ctx_error = err.get("ctx", {}).get("error")
    if isinstance(ctx_error, ConfigError):
        return ConfigError(".".join(p for p in (path, ctx_error.path) if p), ctx_error.reason)
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] not in ("value_error", "assertion_error") and "input" in err:
        value = err["input"]
        if not isinstance(value, dict):
            msg += f" (got {value!r})"
    return ConfigError(path, msg)


def read_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML config file; raises :class:`ConfigError` with the file's name."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError("", f"config file not found: {p}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("", f"{p}: invalid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError("", f"cannot read config file {p}: {exc.strerror}") from None


def parse_override(text: str) -> Any:
    """A ``--set`` value: a TOML value if it parses as one (``0.001``, ``true``,
    ``["a", "b"]``, ``[1, 2, 3]``), else the text itself."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _nest(overrides: Mapping[str, Any]) -> dict[str, Any]:
    tree: dict[str, Any] = {}
    for path, value in overrides.items():
        if value is None:
            continue
        parts = path.split(".")
        node = tree
        for p in parts[:-1]:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise ConfigError(path, f"{p} is set twice")
            node = nxt
        node[parts[-1]] = value
    return tree


def _merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def _check_override_paths(cls: type[BaseModel], tree: Mapping[str, Any], prefix: str = "") -> None:
    for key, value in tree.items():
        path = f"{prefix}{key}"
        field = cls.model_fields.get(key)
        if field is None:
            if cls.model_config.get("extra") == "ignore":
                continue  # a view of another service's table (e.g. the planner's of [arm])
            raise ConfigError(path, "unknown field")
        ann = field.annotation
        if isinstance(value, dict) and isinstance(ann, type) and issubclass(ann, BaseModel):
            _check_override_paths(ann, value, path + ".")


def load_config(
    cls: type[T],
    path: str | Path | None = None,
    *,
    overrides: Mapping[str, Any] | None = None,
    env: Mapping[str, str] | None = None,
) -> T:
    """Build and validate a ``cls`` config.

    Precedence, lowest first: the model's defaults, the TOML file at ``path`` (other services'
    tables in it are ignored), the environment ``env`` (default ``os.environ``), then
    ``overrides`` (dotted path -> value; a string is parsed by :func:`parse_override`, as from
    ``--set arm.dt_s=0.001``). Raises :class:`ConfigError`.
    """
    data = read_toml(path) if path is not None and str(path) != "" else {}
    ov = {k: parse_override(v) if isinstance(v, str) else v for k, v in (overrides or {}).items()}
    tree = _nest(ov)
    _check_override_paths(cls, tree)
    token = _SOURCES.set(_Sources(data, env))
    try:
        return cls(**tree)
    except ValidationError as exc:
        raise _with_env_source(config_error(exc), env) from None
    finally:
        _SOURCES.reset(token)


def _with_env_source(err: ConfigError, env: Mapping[str, str] | None) -> ConfigError:
    """Name the environment variable in the error when the bad value came from one."""
    var = env_var_name(err.path) if err.path else ""
    names = {k.upper() for k in (os.environ if env is None else env)}
    if var and var in names:
        return ConfigError(f"{err.path} (from ${var})", err.reason)
    return err


def env_var_name(path: str) -> str:
    """Environment variable of a dotted field path: ``zenoh.mode`` -> ``PSM_ZENOH__MODE``."""
    return ENV_PREFIX + path.replace(".", ENV_NESTED_DELIMITER).upper()


def config_to_dict(cfg: BaseModel) -> dict[str, Any]:
    """A plain nested, JSON-able dict of a config (metadata snapshots, ``--print-config``)."""
    return cfg.model_dump(mode="json")


# --------------------------------------------------------------------------------------------
# Command-line integration
# --------------------------------------------------------------------------------------------


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the common bus flags: ``--config``, ``--prefix``, ``--mode``, ``--connect``,
    ``--listen``, ``--multicast/--no-multicast``, ``--low-latency``, ``--log-level``,
    ``--set PATH=VALUE``."""
    g = parser.add_argument_group("bus configuration (flags override env vars override file)")
    g.add_argument("--config", metavar="FILE.toml", help="TOML config or stack file")
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
    out.update(set_items(getattr(args, "set", None) or []))
    return {k: v for k, v in out.items() if v is not None}


def set_items(items: Iterable[str]) -> dict[str, str]:
    """``--set PATH=VALUE`` items as ``{path: text}`` (raises :class:`ConfigError`)."""
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError("", f"--set expects PATH=VALUE, got {item!r}")
        out[key.strip()] = value
    return out


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
