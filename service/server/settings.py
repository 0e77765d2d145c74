"""What ``meniscope serve`` (and ``meniscope bench serve``) is configured by: one pydantic settings object.

Layers, later ones winning: the defaults below (they run as they are), a config file (``--config``,
TOML or JSON, the same keys), environment variables ``MENISCOPE_<KEY>`` (``MENISCOPE_SOURCE``,
``MENISCOPE_PORT``, ``MENISCOPE_FIT__MAX_MODES`` for nested keys), then command-line options.
Every problem is one :class:`MeniscopeError` line naming the setting.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import os
import tomllib
from collections.abc import Mapping
from contextvars import ContextVar
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import parse_qsl, quote, unquote, urlsplit, urlunsplit

from pydantic import Field, SecretStr, ValidationError, model_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from service import DEFAULT_MODELS, DEFAULT_SCENE
from service.analysis.results import FitSettings
from service.errors import MeniscopeError

log = logging.getLogger(__name__)
Method = Literal["network", "direct", "nearest", "nearest-approx"]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]

#: The layers :func:`load_settings` puts below the environment, strongest first: the config file's table,
#: then fallbacks (pydantic-settings builds its sources per class, so they are handed over here).
_LAYERS: ContextVar[tuple[dict[str, Any], ...]] = ContextVar("meniscope_settings_layers", default=())


def default_data_dir() -> Path:
    """``$XDG_CACHE_HOME/meniscope`` (``~/.cache/meniscope``): history database and the demo recording."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "meniscope"


class ServiceSettings(BaseSettings):
    """Every setting of the monitoring service, with defaults that run on a fresh install."""

    model_config = SettingsConfigDict(env_prefix="MENISCOPE_", env_nested_delimiter="__", extra="forbid", frozen=True)

    # --- acquisition and inference
    source: str | None = Field(
        None, max_length=4096, description="frame source URI or recording path; none: the demo recording"
    )
    recordings_dir: Path | None = Field(None, description="file sources must lie here (default DATA_DIR/recordings)")
    scene: Path = DEFAULT_SCENE
    models: Path = DEFAULT_MODELS
    method: Method = Field(
        "network", description="network (fast), direct, nearest or nearest-approx (accurate, needs nearest_database)"
    )
    nearest_database: Path | None = Field(None, description="render database of the nearest methods")
    read_frames: Annotated[int, Field(ge=1, le=4096)] = Field(
        64,
        description="frames per source read: a frame waits in the source until its read is full, and is inferred "
        "after the frames read before it",
    )
    batch: Annotated[int, Field(ge=1, le=4096)] = Field(512, description="frames per inference call, at most")
    batch_ms: Positive = Field(
        5.0,
        description="inference latency budget (ms): a call takes no more frames than it infers in this time at "
        "the cost per frame measured so far, so a window's closing frame never waits behind a long call (2 ms "
        "calls cost the frame path enough per call that 90 WebSocket readers on the same two cores took 14 % of "
        "the frames; 5 ms none, with the publish latency no higher)",
    )
    threads: Annotated[int, Field(ge=1, le=64)] = Field(1, description="onnxruntime intra-op threads")
    queue_batches: Annotated[int, Field(ge=1, le=1024)] = Field(
        64, description="source reads waiting for inference before new ones are dropped"
    )
    # --- segmentation and fit
    ejection_hz: Positive | None = Field(100.0, description="expected ejection rate: no two within half a period")
    ejection_ratio: Positive = Field(
        2.0,
        description="an ejection's burst of frame change above the change of the "
        "frames before it, as a multiple of their median change",
    )
    activity_threshold: Positive | None = Field(
        None,
        description="deprecated and ignored (a warning says so): the robust sigmas of frame change of the former "
        "threshold rule, which the ejection detector replaced; its sensitivity is ejection_ratio",
    )
    max_window_s: Positive = Field(0.05, description="a window is cut (not fitted as one) beyond this")
    trigger: Literal["video", "printer"] = Field(
        "video",
        description="what cuts the windows: the ejections the video shows, or the printer's trigger "
        "(POST /api/v1/ejections, trigger_zmq), which the video then checks",
    )
    trigger_zmq: str | None = Field(
        None,
        description="ZeroMQ endpoint to subscribe to for the printer's ejection "
        'events (JSON {"frame": N} or {"time_s": T}); empty: none',
    )
    trigger_wait_s: Positive = Field(2e-3, description="how long frames wait for a late printer event (trigger)")
    fit: FitSettings = FitSettings()
    fit_workers: Annotated[int, Field(ge=1, le=16)] = Field(1, description="processes fitting windows")
    fit_nice: Annotated[int, Field(ge=0, le=19)] = Field(
        5,
        description="niceness of the fit workers, between the frames (0) and the web side (web_nice): lower "
        "favours fresh windows, higher favours frames",
    )
    refine: bool = Field(
        False,
        description="refine windows by synthesis (as meniscope analyze --refine) on a lane of their own at the "
        "lowest CPU priority: the newest closed window each time the lane is free, published as an update of the "
        "same window id; the others are skipped",
    )
    refine_nice: Annotated[int, Field(ge=0, le=19)] = Field(
        19,
        description="niceness of the refinement lane's process (19, the lowest priority: the frames, the fits and "
        "the web side first; lower: refined windows sooner, at their cost)",
    )
    # --- publishing
    web_nice: Annotated[int, Field(ge=0, le=19)] = Field(
        15,
        description="niceness of the web side's requests and WebSocket clients: higher favours frames and fits",
    )
    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=0, le=65535)] = 8000
    token: SecretStr | None = Field(
        None,
        description="bearer token every changing request needs once set (and "
        "set it before a service bound beyond loopback can be changed)",
    )
    allowed_hosts: list[str] | None = Field(
        None,
        description="Host header names accepted (DNS rebinding guard); none: the names of the bound address, "
        "every name when bound to all interfaces",
    )
    allowed_origins: list[str] = Field([], description="browser origins besides the service's own that may open /ws")
    zmq_publish: str | None = Field("tcp://127.0.0.1:5556", description="ZeroMQ PUB endpoint; empty: none")
    data_dir: Path = Field(default_factory=default_data_dir)
    retention_days: Positive = 7.0
    retention_windows: Annotated[int, Field(ge=1)] = 1_000_000
    trace_hz: Positive = Field(10.0, description="live trace messages per second")
    trace_frames: Annotated[int, Field(ge=16, le=8192)] = Field(400, description="frames per trace message")
    client_queue: Annotated[int, Field(ge=1, le=10_000)] = Field(64, description="messages a WebSocket client may lag")
    retry_max_s: Positive = Field(30.0, description="longest wait between attempts to reopen a failed source")

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        return init_settings, env_settings, *(_Table(settings_cls, data) for data in _LAYERS.get())

    @model_validator(mode="after")
    def _checked(self) -> ServiceSettings:
        if self.activity_threshold is not None:  # config files written before the detector keep working
            log.warning(
                "setting activity_threshold is deprecated and ignored: ejections are found by their burst of frame "
                "change (ejection_ratio, default 2)"
            )
        if self.method.startswith("nearest") and self.nearest_database is None:
            raise ValueError(f"method {self.method!r} needs nearest_database (a `meniscope dataset` folder)")
        if self.source is not None:
            try:
                resolve_source(self.source, self.recordings_folder)
            except MeniscopeError as exc:  # a validation error like any other: one line naming the setting
                raise ValueError(f"source: {exc}") from None
        return self

    @property
    def source_name(self) -> str:
        """What published windows name their source by: ``source`` as set, or "demo"."""
        return self.source or "demo"

    @property
    def recordings_folder(self) -> Path:
        return (self.recordings_dir or self.data_dir / "recordings").expanduser().resolve()

    @property
    def loopback(self) -> bool:
        """True when only this machine can reach the HTTP port."""
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False

    def public(self) -> dict[str, Any]:
        """JSON-safe view for GET /api/v1/config: the token shown only as set or not."""
        data = self.model_dump(mode="json", exclude={"token"})
        data["token_set"] = self.token is not None
        return data


class _Table(PydanticBaseSettingsSource):
    """One layer of settings given as a table (a config file's, or fallbacks)."""

    def __init__(self, settings_cls: type[BaseSettings], data: dict[str, Any]) -> None:
        super().__init__(settings_cls)
        self._data = data

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:
        return self._data.get(field_name), field_name, False

    def __call__(self) -> dict[str, Any]:
        return dict(self._data)


def read_config(path: Path) -> dict[str, Any]:
    """A config file's table of settings."""
    try:
        text = path.read_text()
        data = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except OSError as exc:
        raise MeniscopeError(path, f"cannot read the config: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, ValueError) as exc:  # JSONDecodeError and TOMLDecodeError are ValueErrors
        raise MeniscopeError(path, f"not a TOML or JSON config: {exc}") from None
    if not isinstance(data, dict):
        raise MeniscopeError(path, "the config must be a table of settings")
    return data


def load_settings(
    config: Path | None = None, fallbacks: Mapping[str, Any] | None = None, **overrides: Any
) -> ServiceSettings:
    """Settings from defaults, ``fallbacks``, ``config``, the environment and ``overrides`` (later ones
    winning; None values ignored), validated once, so that an override mends a bad value beneath it.

    ``fallbacks`` hold only where no config file, environment variable or override sets the key
    (``meniscope serve --source REC`` makes REC's folder the recordings folder unless one is set).
    """
    layers = (
        read_config(config) if config is not None else {},
        {k: v for k, v in (fallbacks or {}).items() if v is not None},
    )
    token = _LAYERS.set(layers)
    try:
        return ServiceSettings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        key = str(exc.errors()[0]["loc"][0]) if exc.errors()[0]["loc"] else ""
        raise settings_error(exc, _origin(key, config, layers[0], overrides)) from None
    finally:
        _LAYERS.reset(token)


def _origin(key: str, config: Path | None, table: Mapping[str, Any], overrides: Mapping[str, Any]) -> Path | str | None:
    """Where the value of setting ``key`` came from, strongest first: an option, its environment variable, the
    config file (None: a default or fallback), so that an error names what the user has to change."""
    variable = f"MENISCOPE_{key.upper()}"
    if overrides.get(key) is not None:
        return f"--{key.replace('_', '-')}"
    if any(name.upper() == variable or name.upper().startswith(variable + "__") for name in os.environ):
        return variable
    return config if key in table or key not in ServiceSettings.model_fields else None


def settings_error(exc: ValidationError, where: Path | str | None = None) -> MeniscopeError:
    """The first problem of a validation error as one line naming the setting."""
    err = exc.errors()[0]
    name = ".".join(str(p) for p in err["loc"]) or "settings"
    if err["type"] == "extra_forbidden":
        return MeniscopeError(where or "settings", f"unknown setting {name!r}")
    msg = str(err["msg"]).removeprefix("Value error, ")
    return MeniscopeError(where or "settings", f"{name}: {msg}" if err["loc"] else msg)


def recording_folder(source: str) -> Path | None:
    """The folder of the recording a source names, as a bare path or a ``file://`` URI; None for other schemes.

    ``meniscope serve --source`` makes it the recordings folder unless one is set, so that both spellings
    the README gives (``/data/run.cine``, ``file:///data/run.cine?speed=1&loop=true``) work alike.
    """
    parts = urlsplit(source) if "://" in source else None
    if parts is not None and parts.scheme.lower() != "file":
        return None
    raw = unquote(parts.path) if parts is not None else source
    return Path(raw).expanduser().resolve().parent


def resolve_source(uri: str, recordings: Path) -> str:
    """``uri`` with a file source made absolute inside ``recordings``; refuses one that would leave it.

    Relative paths are taken from ``recordings``; symbolic links and ``..`` are resolved before the
    check, so nothing outside the folder can be named. A ``sim://`` source renders the service's own
    scene (the supervisor passes it), so its URI may not name a file either. Other schemes (cameras,
    sockets) pass as given.
    """
    parts = urlsplit(uri) if "://" in uri else None
    if parts is not None and parts.scheme.lower() == "sim" and "scene" in dict(parse_qsl(parts.query)):
        raise MeniscopeError(uri, "sim:// renders the service's scene (setting scene): leave scene out of the URI")
    if parts is not None and parts.scheme.lower() != "file":
        return uri
    raw = unquote(parts.path) if parts is not None else uri
    path = (recordings / Path(raw).expanduser()).resolve()
    if not path.is_relative_to(recordings):
        raise MeniscopeError(
            uri,
            f"file sources must lie in the recordings folder {recordings} "
            "(setting recordings_dir, MENISCOPE_RECORDINGS_DIR)",
        )
    query = parts.query if parts is not None else ""
    return urlunsplit(("file", "", quote(str(path)), query, ""))
