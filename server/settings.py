"""Server settings: environment variables with the PHIM_ prefix, overridden by `phim serve` flags.

`Settings` is every field of `server.setting_fields.SettingFields` (what can be set, one value at a time),
plus the rules across settings (security first: nothing open beyond loopback without a guard) and what each
part of the server gets from them. This module imports pydantic and the contract only, so `phim serve
--help` answers without torch.
"""

from __future__ import annotations

import ipaddress
from typing import TYPE_CHECKING, Any

from pydantic import model_validator

from contract import Limits
from contract.ros2 import default_detections_topic, default_stream_id, node_name
from server.setting_fields import SettingFields, SettingGroup

__all__ = ["MAX_GRAPH_BATCH", "SettingGroup", "Settings", "endpoint_is_loopback", "is_loopback"]

MAX_GRAPH_BATCH = 32  # the largest batch bucket of the fixed-shape step (model/graph/buckets.py)

if TYPE_CHECKING:
    from ros.live_view import LiveViewConfig
    from ros.node import Ros2Config
    from server.worker import WorkerConfig
    from server.zenoh_transport import ZenohConfig


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


class Settings(SettingFields):
    """Every setting of `phim serve` (`SettingFields`), checked together."""

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
