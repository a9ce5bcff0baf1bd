"""Server settings: environment variables with the PHIM_ prefix, overridden by `phim serve` flags.

Lists (zenoh endpoints) are comma-separated: PHIM_ZENOH_CONNECT=tcp/router:7447,tcp/b:7447. This module
imports pydantic and the contract only, so `phim serve --help` answers without torch.
"""

from __future__ import annotations

import enum
import ipaddress
import os
import socket
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from contract import (
    DEFAULT_HTTP_PORT,
    DEFAULT_MIN_SCORE,
    DEFAULT_ZENOH_ENDPOINT,
    STREAM_ID_PATTERN,
    Limits,
)
from contract.ros2 import check_topic, default_detections_topic, default_stream_id, node_name
from server.auth import TokenFile

MAX_GRAPH_BATCH = 32  # the largest batch bucket of the fixed-shape step (model/graph/buckets.py)

if TYPE_CHECKING:
    from ros.live_view import LiveViewConfig
    from ros.node import Ros2Config
    from server.worker import WorkerConfig
    from server.zenoh_transport import ZenohConfig

Endpoints = Annotated[tuple[str, ...], NoDecode]
EgoBox = Annotated[tuple[float, ...] | None, NoDecode]


def is_loopback(host: str) -> bool:
    """Whether an HTTP bind address is reachable from this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


def endpoint_is_loopback(endpoint: str) -> bool:
    """Whether a zenoh endpoint (`tcp/127.0.0.1:7447`, `tls/[::1]:7447#...`) is reachable from this machine
    only: a loopback host, or a unix socket."""
    proto, _, rest = endpoint.partition("/")
    if proto == "unixsock-stream":
        return True
    address = rest.split("?", 1)[0].split("#", 1)[0]
    host = address.rsplit(":", 1)[0] if ":" in address else address
    return is_loopback(host.strip("[]"))


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


class Settings(BaseSettings):
    """Every setting of `phim serve`: an environment variable PHIM_<NAME>, overridden by the flag --<name>
    (both generated from this class: server/cli.py)."""

    model_config = SettingsConfigDict(env_prefix="PHIM_", extra="forbid", frozen=True)

    # HTTP
    host: Annotated[str, TRANSPORTS] = Field("127.0.0.1", description="HTTP bind address.")
    port: Annotated[int, TRANSPORTS] = Field(DEFAULT_HTTP_PORT, ge=0, le=65535, description="HTTP port.")
    tls_cert: Annotated[Path | None, SECURITY] = Field(
        None, description="Serve HTTPS with this PEM certificate (chain) and --tls-key."
    )
    tls_key: Annotated[Path | None, SECURITY] = Field(None, description="The PEM private key of --tls-cert.")
    http_header_timeout_s: Annotated[float, LIMITS] = Field(
        10.0, gt=0, description="Seconds for a request's headers."
    )
    http_body_timeout_s: Annotated[float, LIMITS] = Field(
        30.0, gt=0, description="Seconds for a request's body, after its headers."
    )
    http_max_header_bytes: Annotated[int, LIMITS] = Field(
        32768, ge=1024, description="Request line and headers at most (bytes)."
    )
    http_max_headers: Annotated[int, LIMITS] = Field(
        100, ge=8, description="Header fields in one request at most."
    )
    # model
    checkpoint: Annotated[Path | None, MODEL] = Field(
        None, description="Weights [default: the embedded default model]."
    )
    config: Annotated[str | None, MODEL] = Field(
        None, description="The checkpoint's config; alone: serve it untrained."
    )
    refiner: Annotated[bool, MODEL] = Field(
        True, description="Refine each box from the points (docs/model.md)."
    )
    min_score: Annotated[float, MODEL] = Field(
        DEFAULT_MIN_SCORE, ge=0.0, le=1.0, description="Replies leave out boxes scored below this."
    )
    ego_footprint: Annotated[EgoBox, MODEL] = Field(
        None, description="Ego box x_min,x_max,y_min,y_max (m), or off [default: the config's]."
    )
    device: Annotated[str, MODEL] = Field(
        "auto", pattern=r"^(auto|cpu|cuda(:\d+)?)$", description="auto, cpu, cuda or cuda:N."
    )
    threads: Annotated[int, MODEL] = Field(0, ge=0, description="Torch CPU threads (0: torch's default).")
    warmup_sectors: Annotated[int, MODEL] = Field(
        5, ge=0, description="Warm-up forwards before the worker is ready."
    )
    engine: Annotated[Literal["eager", "graph"], MODEL] = Field(
        "eager", description="How a step runs: eager or graph (docs/deployment.md)."
    )
    sector_voxels: Annotated[int, MODEL] = Field(
        0, ge=0, description="graph: voxels buffered per sector (0: the config's)."
    )
    sector_points: Annotated[int, MODEL] = Field(
        49152, ge=0, description="graph: points a sector is padded to (0: the batch's largest)."
    )
    bev_crop: Annotated[bool, MODEL] = Field(
        True, description="graph: after a turn, BEV only around the new sector."
    )
    capacity_headroom: Annotated[float, MODEL] = Field(
        2.0, ge=1.0, description="graph: capacities over the warm-up turn's."
    )
    precision: Annotated[Literal["fp32", "bf16"], MODEL] = Field(
        "fp32", description="fp32, or bf16 autocast (meant for CUDA)."
    )
    # scheduler and stream table
    max_batch: Annotated[int, LIMITS] = Field(8, ge=1, description="Streams per forward.")
    max_queued_points: Annotated[int, LIMITS] = Field(
        4_000_000, ge=1, description="Queued points, all streams together (beyond: 503)."
    )
    max_wait_ms: Annotated[float, LIMITS] = Field(
        0.0, ge=0, description="How long the oldest sector may wait for a fuller batch."
    )
    queue_size: Annotated[int, LIMITS] = Field(
        64, ge=1, description="Queued sectors, all streams together (beyond: 503)."
    )
    deadline_ms: Annotated[float, LIMITS] = Field(
        2000.0, gt=0, description="A sector not started by then gets 504."
    )
    idle_timeout_s: Annotated[float, LIMITS] = Field(
        10.0, gt=0, description="Streams idle this long are evicted."
    )
    max_streams: Annotated[int, LIMITS] = Field(
        256, ge=1, description="Live streams at most (graph: the state slots)."
    )
    drain_timeout_s: Annotated[float, LIMITS] = Field(
        10.0, ge=0, description="On shutdown, answer queued sectors this long."
    )
    # tenants (docs/security.md): a stream's tenant is its token's prefix, else its ID up to the first '.'
    tenant_max_streams: Annotated[int | None, LIMITS] = Field(
        None, ge=1, description="Live streams a tenant may hold [default: max_streams/2]."
    )
    tenant_queue_size: Annotated[int | None, LIMITS] = Field(
        None, ge=1, description="Queued sectors a tenant is guaranteed [default: queue_size/2]."
    )
    # limits on a sector message
    max_body_bytes: Annotated[int, LIMITS] = Field(
        64 * 2**20, ge=1024, description="Largest sector message (bytes)."
    )
    max_points: Annotated[int, LIMITS] = Field(1_000_000, ge=1, description="Points per sector at most.")
    max_string_len: Annotated[int, LIMITS] = Field(256, ge=1, description="Longest stream ID or field name.")
    max_fields: Annotated[int, LIMITS] = Field(16, ge=4, description="Point columns at most.")
    # zenoh
    zenoh_enabled: Annotated[bool, TRANSPORTS] = Field(True, description="Serve over zenoh as well as HTTP.")
    zenoh_mode: Annotated[Literal["peer", "client", "router"], TRANSPORTS] = Field(
        "peer", description="Zenoh session mode."
    )
    zenoh_listen: Annotated[Endpoints, TRANSPORTS] = Field(
        (DEFAULT_ZENOH_ENDPOINT,), description="Zenoh endpoints to listen on (a client: none)."
    )
    zenoh_connect: Annotated[Endpoints, TRANSPORTS] = Field(
        (), description="Zenoh endpoints to connect to (a router, peers)."
    )
    zenoh_config_file: Annotated[Path | None, SECURITY] = Field(
        None, description="A zenoh JSON5 config (ACL, mTLS or user/password)."
    )
    zenoh_multicast_scouting: Annotated[bool, TRANSPORTS] = Field(
        False, description="Zenoh multicast scouting."
    )
    zenoh_shared_keys: Annotated[bool, TRANSPORTS] = Field(
        True, description="Also answer phim/v1/streams/... (one worker alone)."
    )
    # ROS 2 bridge (docs/ros2.md): rmw_zenoh topics through the zenoh session above
    ros2_points: Annotated[str | None, ROS2] = Field(
        None, description="PointCloud2 topic to take scans from (unset: no bridge)."
    )
    ros2_detections: Annotated[str | None, ROS2] = Field(
        None, description="Detection3DArray topic [default: /NS/detections, NS the points topic's namespace]."
    )
    ros2_markers: Annotated[str | None, ROS2] = Field(
        None, description="MarkerArray topic for RViz (unset: none)."
    )
    ros2_domain_id: Annotated[int, ROS2] = Field(0, ge=0, description="The ROS graph's ROS_DOMAIN_ID.")
    ros2_stream_id: Annotated[str | None, ROS2] = Field(
        None,
        pattern=STREAM_ID_PATTERN,
        max_length=128,
        description="The scans' stream [default: the points topic's namespace].",
    )
    ros2_intensity_scale: Annotated[float, ROS2] = Field(
        1.0, gt=0, description="Intensity factor to 0..1 (1/255: drivers of 0..255)."
    )
    ros2_partial_scans: Annotated[bool, ROS2] = Field(
        False, description="Each PointCloud2 is a piece of a turn."
    )
    # live view (docs/ros2.md)
    foxglove_port: Annotated[int | None, ROS2] = Field(
        None, ge=0, le=65535, description="Foxglove live view port (0: a free one; unset: none)."
    )
    foxglove_host: Annotated[str, ROS2] = Field("127.0.0.1", description="The live view's bind address.")
    # identity and logs
    worker_id: Annotated[str, LOGS] = Field(
        default_factory=default_worker_id,
        pattern=STREAM_ID_PATTERN,
        max_length=128,
        description="This worker's ID, unique in a fleet [default: host-pid].",
    )
    log_level: Annotated[Literal["debug", "info", "warning", "error"], LOGS] = Field(
        "info", description="Log level."
    )
    log_format: Annotated[Literal["text", "json"], LOGS] = Field(
        "text", description="Logs on stderr: text lines, or JSON lines."
    )
    access_log: Annotated[bool, LOGS] = Field(False, description="uvicorn's access log: a line per request.")
    # access (docs/security.md)
    auth_tokens: Annotated[Path | None, SECURITY] = Field(
        None, description="Token file (phim auth add-token) HTTP routes need."
    )
    public_metrics: Annotated[bool, LOGS] = Field(
        False, description="With --auth-tokens: /metrics needs no token."
    )
    insecure: Annotated[bool, SECURITY] = Field(
        False, description="Allow HTTP, zenoh, live view open beyond loopback."
    )

    @model_validator(mode="after")
    def _batch_fits_the_buckets(self) -> Settings:
        if self.engine != "eager" and self.max_batch > MAX_GRAPH_BATCH:
            raise ValueError(
                f"max_batch {self.max_batch}: the {self.engine} engine runs {MAX_GRAPH_BATCH} at most"
            )
        return self

    @model_validator(mode="after")
    def _open_only_on_loopback(self) -> Settings:
        if self.auth_tokens is None and not self.insecure and not is_loopback(self.host):
            raise ValueError(
                f"host {self.host}: beyond loopback without --auth-tokens anyone who reaches the port may "
                "send to, read and end every stream; give --auth-tokens FILE (phim auth add-token), or "
                "--insecure (PHIM_INSECURE=1) to accept that"
            )
        return self

    @model_validator(mode="before")
    @classmethod
    def _a_zenoh_client_listens_nowhere(cls, data: Any) -> Any:
        # unless asked: a second worker on the host would find the default endpoint taken
        if isinstance(data, dict) and data.get("zenoh_mode") == "client" and "zenoh_listen" not in data:
            return {**data, "zenoh_listen": ()}
        return data

    @model_validator(mode="after")
    def _zenoh_guarded(self) -> Settings:
        """zenoh follows HTTP's rule: reachable beyond loopback, or with --auth-tokens reachable at all, it
        needs a config file (whose ACL, mTLS or user/password the transport checks when it reads it)."""
        exposed = self.zenoh_exposed()
        if exposed and not self.insecure and self.zenoh_config_file is None:
            raise ValueError(
                f"{exposed} zenoh without an ACL lets anyone who reaches it send into every stream and read "
                "every stream's detections; give --zenoh-config-file FILE with an ACL, mTLS or user/password "
                "(deploy/zenoh/), --zenoh-listen '' (and no --zenoh-connect) or --no-zenoh, or --insecure "
                "(PHIM_INSECURE=1) to accept that"
            )
        if exposed and not self.insecure and self.zenoh_config_file and self.zenoh_config_file.is_file():
            import zenoh  # the file's contents (a missing file fails where zenoh reads it, at start-up)

            from server.zenoh_transport import require_guard

            try:
                conf = zenoh.Config.from_file(str(self.zenoh_config_file))
            except zenoh.ZError as e:
                raise ValueError(f"zenoh config file {self.zenoh_config_file}: {e}") from None
            require_guard(conf, str(self.zenoh_config_file))
        return self

    def zenoh_exposed(self) -> str | None:
        """Why this worker's zenoh needs a guard (None: it does not): listening beyond loopback, or reachable
        at all while HTTP needs tokens (a session that listens and connects nowhere is reachable by none)."""
        if not self.zenoh_enabled and self.ros2_points is None:
            return None
        wide = [e for e in self.zenoh_listen if not endpoint_is_loopback(e)]
        if wide:
            return f"zenoh_listen {','.join(wide)}: beyond loopback"
        reached = bool(self.zenoh_listen or self.zenoh_connect or self.zenoh_multicast_scouting)
        return "--auth-tokens: HTTP needs a token, but" if self.auth_tokens is not None and reached else None

    @model_validator(mode="after")
    def _live_view_only_on_loopback(self) -> Settings:
        # the Foxglove server has no authentication: --auth-tokens does not cover it
        if self.foxglove_port is not None and not self.insecure and not is_loopback(self.foxglove_host):
            raise ValueError(
                f"foxglove_host {self.foxglove_host}: the live view has no authentication, so anyone who "
                "reaches the port sees every stream's points and boxes; give --insecure (PHIM_INSECURE=1) "
                "to accept that, or keep it on loopback (an SSH tunnel or an authenticating proxy)"
            )
        return self

    @model_validator(mode="after")
    def _cert_with_its_key(self) -> Settings:
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key: give both (HTTPS) or neither (HTTP)")
        for path in (self.tls_cert, self.tls_key):
            if path is not None and not path.is_file():
                raise ValueError(f"{path}: no such file")
        return self

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

    def limits(self) -> Limits:
        return Limits(self.max_body_bytes, self.max_points, self.max_string_len, self.max_fields)

    def worker_config(self) -> WorkerConfig:
        from server.worker import WorkerConfig

        return WorkerConfig(
            worker_id=self.worker_id,
            max_batch=self.max_batch,
            max_wait_ms=self.max_wait_ms,
            queue_size=self.queue_size,
            max_queued_points=self.max_queued_points,
            deadline_ms=self.deadline_ms,
            idle_timeout_s=self.idle_timeout_s,
            max_streams=self.max_streams,
            warmup_sectors=self.warmup_sectors,
            capacity_headroom=self.capacity_headroom,
            min_score=self.min_score,
            tenant_max_streams=self.tenant_max_streams,
            tenant_queue_size=self.tenant_queue_size,
        )

    def live_view_config(self) -> LiveViewConfig:
        from ros.live_view import LiveViewConfig

        assert self.foxglove_port is not None, "no live view without --foxglove-port"
        # its channels outlive a stream's eviction a little: a viewer sees the last boxes, then they go
        return LiveViewConfig(
            host=self.foxglove_host,
            port=self.foxglove_port,
            idle_s=2 * self.idle_timeout_s,
            name=self.worker_id,
        )

    def ros2_config(self) -> Ros2Config:
        """The bridge's settings, defaults filled in."""
        from ros.node import Ros2Config

        assert self.ros2_points is not None, "no ROS 2 bridge without --ros2-points"
        return Ros2Config(
            points=self.ros2_points,
            detections=self.ros2_detections or default_detections_topic(self.ros2_points),
            markers=self.ros2_markers,
            domain_id=self.ros2_domain_id,
            stream_id=self.ros2_stream_id or default_stream_id(self.ros2_points),
            intensity_scale=self.ros2_intensity_scale,
            partial_scans=self.ros2_partial_scans,
            node_name=node_name(self.worker_id),
        )

    def zenoh_config(self) -> ZenohConfig:
        from server.zenoh_transport import ZenohConfig

        return ZenohConfig(
            mode=self.zenoh_mode,
            listen=tuple(self.zenoh_listen),
            connect=tuple(self.zenoh_connect),
            multicast_scouting=self.zenoh_multicast_scouting,
            config_file=None if self.zenoh_config_file is None else str(self.zenoh_config_file),
            shared_keys=self.zenoh_shared_keys,
            guard_required=self.zenoh_exposed() is not None and not self.insecure,
        )
