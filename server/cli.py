"""`phim serve`."""

from __future__ import annotations

import logging
import signal
from pathlib import Path
from typing import Annotated

import typer

ZENOH = "zenoh"


def serve(
    host: Annotated[str | None, typer.Option(help="HTTP bind address [PHIM_HOST; 127.0.0.1]")] = None,
    port: Annotated[int | None, typer.Option(help="HTTP port [PHIM_PORT; 8080]")] = None,
    checkpoint: Annotated[
        Path | None,
        typer.Option(help="weights to serve [PHIM_CHECKPOINT; default: the embedded default model]"),
    ] = None,
    config: Annotated[
        str | None,
        typer.Option(help="the checkpoint's config (checked); without one: serve it untrained [PHIM_CONFIG]"),
    ] = None,
    device: Annotated[str | None, typer.Option(help="auto, cpu, cuda, cuda:N [PHIM_DEVICE; auto]")] = None,
    threads: Annotated[int | None, typer.Option(help="torch CPU threads, 0: default [PHIM_THREADS]")] = None,
    max_batch: Annotated[int | None, typer.Option(help="streams per forward [PHIM_MAX_BATCH; 8]")] = None,
    max_wait_ms: Annotated[
        float | None, typer.Option(help="wait for a fuller batch [PHIM_MAX_WAIT_MS; 0]")
    ] = None,
    queue_size: Annotated[
        int | None, typer.Option(help="queued sectors before 503 [PHIM_QUEUE_SIZE; 64]")
    ] = None,
    deadline_ms: Annotated[float | None, typer.Option(help="queue deadline [PHIM_DEADLINE_MS; 2000]")] = None,
    idle_timeout_s: Annotated[
        float | None, typer.Option(help="evict idle streams [PHIM_IDLE_TIMEOUT_S; 10]")
    ] = None,
    max_streams: Annotated[int | None, typer.Option(help="live stream limit [PHIM_MAX_STREAMS; 256]")] = None,
    drain_timeout_s: Annotated[
        float | None,
        typer.Option(help="on shutdown, keep running queued sectors this long [PHIM_DRAIN_TIMEOUT_S]"),
    ] = None,
    warmup_sectors: Annotated[
        int | None, typer.Option(help="warm-up forwards [PHIM_WARMUP_SECTORS; 5]")
    ] = None,
    max_points: Annotated[int | None, typer.Option(help="points per sector [PHIM_MAX_POINTS]")] = None,
    max_string_len: Annotated[
        int | None, typer.Option(help="stream ID/field names [PHIM_MAX_STRING_LEN]")
    ] = None,
    max_fields: Annotated[int | None, typer.Option(help="point columns [PHIM_MAX_FIELDS; 16]")] = None,
    max_body_bytes: Annotated[
        int | None, typer.Option(help="sector message size [PHIM_MAX_BODY_BYTES]")
    ] = None,
    zenoh: Annotated[bool | None, typer.Option("--zenoh/--no-zenoh", help="[PHIM_ZENOH_ENABLED; on]")] = None,
    zenoh_mode: Annotated[
        str | None, typer.Option(help="peer, client, router [PHIM_ZENOH_MODE; peer]")
    ] = None,
    zenoh_listen: Annotated[
        str | None, typer.Option(help="comma-separated endpoints [PHIM_ZENOH_LISTEN; tcp/127.0.0.1:7447]")
    ] = None,
    zenoh_connect: Annotated[str | None, typer.Option(help="comma-separated [PHIM_ZENOH_CONNECT]")] = None,
    zenoh_config_file: Annotated[
        Path | None, typer.Option(help="zenoh JSON5 config [PHIM_ZENOH_CONFIG_FILE]")
    ] = None,
    zenoh_multicast_scouting: Annotated[
        bool | None, typer.Option(help="zenoh multicast scouting [PHIM_ZENOH_MULTICAST_SCOUTING; off]")
    ] = None,
    worker_id: Annotated[str | None, typer.Option(help="[PHIM_WORKER_ID; hostname-pid]")] = None,
    log_level: Annotated[
        str | None, typer.Option(help="debug, info, warning, error [PHIM_LOG_LEVEL]")
    ] = None,
) -> None:
    """Serve the detector over HTTP and zenoh until SIGTERM/SIGINT (then drain and exit)."""
    flags = {k: v for k, v in locals().items() if v is not None}
    if ZENOH in flags:
        flags["zenoh_enabled"] = flags.pop(ZENOH)
    run_server(flags)


def run_server(flags: dict[str, object]) -> None:
    import torch
    import uvicorn
    from pydantic import ValidationError

    from phim.process import tune_malloc
    from server.app import create_app
    from server.settings import Settings

    try:
        settings = Settings(**flags)  # type: ignore[arg-type]  # flags override PHIM_* environment variables
    except ValidationError as e:
        raise typer.BadParameter(str(e)) from None
    logging.basicConfig(
        level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=True
    )
    tuned = tune_malloc()
    if settings.threads:
        torch.set_num_threads(settings.threads)
    logging.getLogger("phim.serve").info(
        "phim serve: http://%s:%d worker=%s zenoh=%s malloc_tuned=%s torch_threads=%d",
        settings.host,
        settings.port,
        settings.worker_id,
        settings.zenoh_enabled,
        tuned,
        torch.get_num_threads(),
    )
    config = uvicorn.Config(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_config=None,
        log_level=settings.log_level,
        ws="none",
        lifespan="on",
        timeout_graceful_shutdown=max(1, round(settings.drain_timeout_s)),
    )
    server = uvicorn.Server(config)
    for sig in (signal.SIGINT, signal.SIGTERM):  # uvicorn re-raises the signal after its graceful shutdown:
        signal.signal(sig, _after_shutdown)  # end with exit code 0 instead of dying by it again
    server.run()
    if not server.started:
        raise typer.Exit(code=3)  # startup failed (the log says why)


def _after_shutdown(sig: int, frame: object) -> None:
    logging.getLogger("phim.serve").info("stopped by signal %d after a graceful shutdown", sig)
