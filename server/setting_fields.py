"""Every `phim serve` setting: its type, default, help section (`SettingGroup`, named in the annotation) and
one-line help, and what makes one value valid on its own (`SettingFields`). `server.settings.Settings` adds
the rules across settings and what each part of the server gets from them. Lists (zenoh endpoints) are
comma-separated: PHIM_ZENOH_CONNECT=tcp/router:7447,tcp/b:7447. pydantic and the contract only (no torch).
"""

from __future__ import annotations

import enum
import os
import socket
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from contract import DEFAULT_HTTP_PORT, DEFAULT_MIN_SCORE, DEFAULT_ZENOH_ENDPOINT, STREAM_ID_PATTERN
from contract.ros2 import check_topic
from server.auth import TokenFile

Endpoints = Annotated[tuple[str, ...], NoDecode]
EgoBox = Annotated[tuple[float, ...] | None, NoDecode]


class SettingGroup(enum.Enum):
    """The section of `phim serve --help` a setting is listed in (its annotation names it); the value is the
    section's title, in the order they are listed."""

    MODEL = "Model and engine"
    TRANSPORTS = "Transports (HTTP, zenoh)"
    LIMITS = "Limits (batching, streams, tenants, sizes)"
    SECURITY = "Security (tokens, TLS, zenoh guard)"
    ROS2 = "ROS 2 and live view (docs/ros2.md)"
    LOGS = "Identity, logs and metrics"


# the annotations' short names: `host: Annotated[str, TRANSPORTS]`
MODEL, TRANSPORTS, LIMITS = SettingGroup.MODEL, SettingGroup.TRANSPORTS, SettingGroup.LIMITS
SECURITY, ROS2, LOGS = SettingGroup.SECURITY, SettingGroup.ROS2, SettingGroup.LOGS


def default_worker_id() -> str:
    return f"{socket.gethostname()}-{os.getpid()}"


def setting(default: Any, help: str, **checks: Any) -> Any:
    """A setting's pydantic field: its default, its one-line help (`phim serve --help`; "[default: ...]" at
    its end says what an unset value means) and its checks (ge, le, pattern, ...)."""
    return Field(default, description=help, **checks)


class SettingFields(BaseSettings):
    """Every setting of `phim serve`: an environment variable PHIM_<NAME>, overridden by the flag --<name>
    (both generated from these fields: server/cli.py)."""

    model_config = SettingsConfigDict(env_prefix="PHIM_", extra="forbid", frozen=True)

    # HTTP
    host: Annotated[str, TRANSPORTS] = setting("127.0.0.1", "HTTP bind address.")
    port: Annotated[int, TRANSPORTS] = setting(DEFAULT_HTTP_PORT, "HTTP port.", ge=0, le=65535)
    tls_cert: Annotated[Path | None, SECURITY] = setting(
        None, "Serve HTTPS with this PEM certificate (chain) and --tls-key."
    )
    tls_key: Annotated[Path | None, SECURITY] = setting(None, "The PEM private key of --tls-cert.")
    http_header_timeout_s: Annotated[float, LIMITS] = setting(10.0, "Seconds for a request's headers.", gt=0)
    http_body_timeout_s: Annotated[float, LIMITS] = setting(
        30.0, "Seconds for a request's body, after its headers.", gt=0
    )
    http_max_header_bytes: Annotated[int, LIMITS] = setting(
        32768, "Request line and headers at most (bytes).", ge=1024
    )
    http_max_headers: Annotated[int, LIMITS] = setting(100, "Header fields in one request at most.", ge=8)
    # model
    checkpoint: Annotated[Path | None, MODEL] = setting(
        None, "Weights [default: the embedded default model]."
    )
    config: Annotated[str | None, MODEL] = setting(
        None, "The checkpoint's config; alone: serve it untrained."
    )
    refiner: Annotated[bool, MODEL] = setting(True, "Refine each box from the points (docs/model.md).")
    min_score: Annotated[float, MODEL] = setting(
        DEFAULT_MIN_SCORE, "Replies leave out boxes scored below this.", ge=0.0, le=1.0
    )
    ego_footprint: Annotated[EgoBox, MODEL] = setting(
        None, "Ego box x_min,x_max,y_min,y_max (m), or off [default: the config's]."
    )
    device: Annotated[str, MODEL] = setting(
        "auto", "auto, cpu, cuda or cuda:N.", pattern=r"^(auto|cpu|cuda(:\d+)?)$"
    )
    threads: Annotated[int, MODEL] = setting(0, "Torch CPU threads (0: torch's default).", ge=0)
    warmup_sectors: Annotated[int, MODEL] = setting(5, "Warm-up forwards before the worker is ready.", ge=0)
    engine: Annotated[Literal["eager", "graph"], MODEL] = setting(
        "eager", "How a step runs: eager or graph (docs/deployment.md)."
    )
    sector_voxels: Annotated[int, MODEL] = setting(
        0, "graph: voxels buffered per sector (0: the config's).", ge=0
    )
    precision: Annotated[Literal["fp32", "bf16"], MODEL] = setting(
        "fp32", "fp32, or bf16 autocast (meant for CUDA)."
    )
    # scheduler and stream table
    max_batch: Annotated[int, LIMITS] = setting(8, "Streams per forward.", ge=1)
    max_queued_points: Annotated[int, LIMITS] = setting(
        4_000_000, "Queued points, all streams together (beyond: 503).", ge=1
    )
    max_wait_ms: Annotated[float, LIMITS] = setting(
        0.0, "How long the oldest sector may wait for a fuller batch.", ge=0
    )
    queue_size: Annotated[int, LIMITS] = setting(
        64, "Queued sectors, all streams together (beyond: 503).", ge=1
    )
    deadline_ms: Annotated[float, LIMITS] = setting(2000.0, "A sector not started by then gets 504.", gt=0)
    idle_timeout_s: Annotated[float, LIMITS] = setting(10.0, "Streams idle this long are evicted.", gt=0)
    max_streams: Annotated[int, LIMITS] = setting(256, "Live streams at most (graph: the state slots).", ge=1)
    drain_timeout_s: Annotated[float, LIMITS] = setting(
        10.0, "On shutdown, answer queued sectors this long.", ge=0
    )
    # tenants (docs/security.md): a stream's tenant is its token's prefix, else its ID up to the first '.'
    tenant_max_streams: Annotated[int | None, LIMITS] = setting(
        None, "Live streams a tenant may hold [default: max_streams/2].", ge=1
    )
    tenant_queue_size: Annotated[int | None, LIMITS] = setting(
        None, "Queued sectors a tenant is guaranteed [default: queue_size/2].", ge=1
    )
    # limits on a sector message
    max_body_bytes: Annotated[int, LIMITS] = setting(64 * 2**20, "Largest sector message (bytes).", ge=1024)
    max_points: Annotated[int, LIMITS] = setting(1_000_000, "Points per sector at most.", ge=1)
    max_string_len: Annotated[int, LIMITS] = setting(256, "Longest stream ID or field name.", ge=1)
    max_fields: Annotated[int, LIMITS] = setting(16, "Point columns at most.", ge=4)
    # zenoh
    zenoh_enabled: Annotated[bool, TRANSPORTS] = setting(True, "Serve over zenoh as well as HTTP.")
    zenoh_mode: Annotated[Literal["peer", "client", "router"], TRANSPORTS] = setting(
        "peer", "Zenoh session mode."
    )
    zenoh_listen: Annotated[Endpoints, TRANSPORTS] = setting(
        (DEFAULT_ZENOH_ENDPOINT,), "Zenoh endpoints to listen on (a client: none)."
    )
    zenoh_connect: Annotated[Endpoints, TRANSPORTS] = setting(
        (), "Zenoh endpoints to connect to (a router, peers)."
    )
    zenoh_config_file: Annotated[Path | None, SECURITY] = setting(
        None, "A zenoh JSON5 config (ACL, mTLS or user/password)."
    )
    zenoh_multicast_scouting: Annotated[bool, TRANSPORTS] = setting(False, "Zenoh multicast scouting.")
    zenoh_shared_keys: Annotated[bool, TRANSPORTS] = setting(
        True, "Also answer phim/v1/streams/... (one worker alone)."
    )
    # ROS 2 bridge (docs/ros2.md): rmw_zenoh topics through the zenoh session above
    ros2_points: Annotated[str | None, ROS2] = setting(
        None, "PointCloud2 topic to take scans from (unset: no bridge)."
    )
    ros2_detections: Annotated[str | None, ROS2] = setting(
        None, "Detection3DArray topic [default: /NS/detections, NS the points topic's namespace]."
    )
    ros2_markers: Annotated[str | None, ROS2] = setting(None, "MarkerArray topic for RViz (unset: none).")
    ros2_domain_id: Annotated[int, ROS2] = setting(0, "The ROS graph's ROS_DOMAIN_ID.", ge=0)
    ros2_stream_id: Annotated[str | None, ROS2] = setting(
        None,
        "The scans' stream [default: the points topic's namespace].",
        pattern=STREAM_ID_PATTERN,
        max_length=128,
    )
    ros2_intensity_scale: Annotated[float, ROS2] = setting(
        1.0, "Intensity factor to 0..1 (1/255: drivers of 0..255).", gt=0
    )
    ros2_partial_scans: Annotated[bool, ROS2] = setting(False, "Each PointCloud2 is a piece of a turn.")
    # live view (docs/ros2.md)
    foxglove_port: Annotated[int | None, ROS2] = setting(
        None, "Foxglove live view port (0: a free one; unset: none).", ge=0, le=65535
    )
    foxglove_host: Annotated[str, ROS2] = setting("127.0.0.1", "The live view's bind address.")
    # identity and logs
    worker_id: Annotated[str, LOGS] = Field(
        default_factory=default_worker_id,
        pattern=STREAM_ID_PATTERN,
        max_length=128,
        description="This worker's ID, unique in a fleet [default: host-pid].",
    )
    log_level: Annotated[Literal["debug", "info", "warning", "error"], LOGS] = setting("info", "Log level.")
    log_format: Annotated[Literal["text", "json"], LOGS] = setting(
        "text", "Logs on stderr: text lines, or JSON lines."
    )
    access_log: Annotated[bool, LOGS] = setting(False, "uvicorn's access log: a line per request.")
    # access (docs/security.md)
    auth_tokens: Annotated[Path | None, SECURITY] = setting(
        None, "Token file (phim auth add-token) HTTP routes need."
    )
    public_metrics: Annotated[bool, LOGS] = setting(False, "With --auth-tokens: /metrics needs no token.")
    insecure: Annotated[bool, SECURITY] = setting(False, "Allow HTTP, zenoh, live view open beyond loopback.")

    @field_validator("sector_voxels")
    @classmethod
    def _sector_voxels_or_the_configs(cls, value: int) -> int:
        if 0 < value < 256:
            raise ValueError(f"{value}: give 0 (the config's) or at least 256")
        return value

    @field_validator("auth_tokens")
    @classmethod
    def _readable_tokens(cls, value: Path | None) -> Path | None:
        if value is not None:
            TokenFile(value)  # TokenFileError (a ValueError) names the file and line
        return value

    @field_validator("ego_footprint", mode="before")
    @classmethod
    def _split_footprint(cls, value: Any) -> Any:
        if isinstance(value, str):
            if value.strip().lower() in ("off", "none"):
                return ()
            return tuple(v.strip() for v in value.split(",") if v.strip())
        return value

    @field_validator("ego_footprint")
    @classmethod
    def _footprint_box(cls, value: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if value is None or value == ():
            return value
        if len(value) != 4 or not (value[0] < value[1] and value[2] < value[3]):
            raise ValueError(
                f"{','.join(f'{v:g}' for v in value)}: expected x_min,x_max,y_min,y_max with x_min < x_max "
                "and y_min < y_max (metres), or 'off'"
            )
        return value

    @field_validator("zenoh_listen", "zenoh_connect", mode="before")
    @classmethod
    def _split_endpoints(cls, value: Any) -> Any:
        if isinstance(value, str):
            return tuple(v.strip() for v in value.split(",") if v.strip())
        return value

    @field_validator("ros2_points", "ros2_detections", "ros2_markers", mode="before")
    @classmethod
    def _ros2_topic(cls, value: Any, info: ValidationInfo) -> Any:
        if value == "":  # PHIM_ROS2_MARKERS= : unset
            return None
        return check_topic(value, info.field_name) if isinstance(value, str) else value

    @field_validator("log_level", "log_format", mode="before")
    @classmethod
    def _lower(cls, value: Any) -> Any:
        return value.lower() if isinstance(value, str) else value
