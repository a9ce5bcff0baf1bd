"""Server settings: environment variables with the PHIM_ prefix, overridden by `phim serve` flags.

Lists (zenoh endpoints) are comma-separated in the environment: PHIM_ZENOH_CONNECT=tcp/router:7447,tcp/b:7447.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from contract import Limits
from server.worker import WorkerConfig

if TYPE_CHECKING:
    from server.zenoh_transport import ZenohConfig

Endpoints = Annotated[tuple[str, ...], NoDecode]


def default_worker_id() -> str:
    return f"{socket.gethostname()}-{os.getpid()}"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="PHIM_", extra="forbid", frozen=True)

    # HTTP
    host: str = "127.0.0.1"
    port: int = Field(8080, ge=0, le=65535)
    # model
    checkpoint: Path | None = None  # None: the embedded default model (server/default_model.py)
    config: str | None = None  # with a checkpoint: the config it must have; without: untrained weights of it
    device: str = Field("auto", pattern=r"^(auto|cpu|cuda(:\d+)?)$")
    threads: int = Field(0, ge=0)  # torch CPU threads; 0 leaves torch's default
    warmup_sectors: int = Field(5, ge=0)
    # scheduler and stream table
    max_batch: int = Field(8, ge=1)
    max_wait_ms: float = Field(0.0, ge=0)
    queue_size: int = Field(64, ge=1)
    deadline_ms: float = Field(2000.0, gt=0)
    idle_timeout_s: float = Field(10.0, gt=0)
    max_streams: int = Field(256, ge=1)
    drain_timeout_s: float = Field(10.0, ge=0)
    # limits on a sector message
    max_body_bytes: int = Field(64 * 2**20, ge=1024)
    max_points: int = Field(1_000_000, ge=1)
    max_string_len: int = Field(256, ge=1)
    max_fields: int = Field(16, ge=4)
    # zenoh
    zenoh_enabled: bool = True
    zenoh_mode: Literal["peer", "client", "router"] = "peer"
    zenoh_listen: Endpoints = ("tcp/127.0.0.1:7447",)
    zenoh_connect: Endpoints = ()
    zenoh_config_file: Path | None = None
    zenoh_multicast_scouting: bool = False
    # identity and logs
    worker_id: str = Field(default_factory=default_worker_id)
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @field_validator("zenoh_listen", "zenoh_connect", mode="before")
    @classmethod
    def _split_endpoints(cls, value: Any) -> Any:
        if isinstance(value, str):
            return tuple(v.strip() for v in value.split(",") if v.strip())
        return value

    @field_validator("log_level", mode="before")
    @classmethod
    def _lower(cls, value: Any) -> Any:
        return value.lower() if isinstance(value, str) else value

    def limits(self) -> Limits:
        return Limits(self.max_body_bytes, self.max_points, self.max_string_len, self.max_fields)

    def worker_config(self) -> WorkerConfig:
        return WorkerConfig(
            worker_id=self.worker_id,
            max_batch=self.max_batch,
            max_wait_ms=self.max_wait_ms,
            queue_size=self.queue_size,
            deadline_ms=self.deadline_ms,
            idle_timeout_s=self.idle_timeout_s,
            max_streams=self.max_streams,
            warmup_sectors=self.warmup_sectors,
        )

    def zenoh_config(self) -> ZenohConfig:
        from server.zenoh_transport import ZenohConfig

        return ZenohConfig(
            mode=self.zenoh_mode,
            listen=tuple(self.zenoh_listen),
            connect=tuple(self.zenoh_connect),
            multicast_scouting=self.zenoh_multicast_scouting,
            config_file=None if self.zenoh_config_file is None else str(self.zenoh_config_file),
        )
