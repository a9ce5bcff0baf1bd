"""Soak: a real `phim serve` under twice its measured capacity for a while, over HTTP and zenoh at once.

    python scripts/soak.py --duration 600        # scripts/soak.sh; CI runs --duration 60 (tests/test_soak.py)

1. starts `phim serve` (synthetic warm-up, HTTP and zenoh on free loopback ports, idle eviction after 5 s);
2. measures its ceiling with a short closed-loop load test (sectors/s);
3. runs open-loop vehicles offering `--factor` x that rate in all (at most 40 sectors/s each, the sensor
   rate; slower where the ceiling is low: never less than two vehicles, one a transport), split over the two
   transports (one `phim loadtest` each, concurrently), sampling the server's RSS every second;
4. checks: every sector answered exactly once (detections or an explicit overload/deadline error: none lost),
   the slopes over the second half (MB/min, least squares) of the RSS less the heap malloc keeps freed
   (`phim_heap_free_bytes` in /metrics: `phim serve` keeps up to 1 GB of it, phim.process.tune_malloc, and
   how much swings with the allocation pattern: 46-352 MB within one minute) under `--max-rss-slope`, and of
   the heap in use (`phim_heap_in_use_bytes`: a leak grows it) under `--max-heap-slope`, and no live streams
   left within the idle timeout (and 3 s) after the load;
5. prints a table, writes `--out` (JSON) if given, exits 1 when a check failed.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

from clients.bench.server import free_port, spawned  # the project installed (scripts/setup.sh)

REPO = Path(__file__).resolve().parents[1]
SECTORS_PER_TURN = 4  # the default model's
SECTORS_PER_S = 10 * SECTORS_PER_TURN  # one vehicle at sensor rate (10 turns/s) at most


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return math.nan


def heap_mb(url: str) -> tuple[float, float]:
    """The server's malloc'd bytes in use and freed but kept (/metrics, glibc only), in MB; NaN without."""
    found = {"phim_heap_in_use_bytes": math.nan, "phim_heap_free_bytes": math.nan}
    with urllib.request.urlopen(f"{url}/metrics", timeout=10) as r:
        for line in r.read().decode().splitlines():
            name, _, value = line.partition(" ")
            if name in found:
                found[name] = float(value) / 2**20
    return found["phim_heap_in_use_bytes"], found["phim_heap_free_bytes"]


def get_json(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())


def slope_mb_per_min(samples: list[tuple[float, float]]) -> float:
    """Least-squares slope of (seconds, MB) samples, in MB per minute."""
    n = len(samples)
    if n < 2:
        return 0.0
    mt = sum(t for t, _ in samples) / n
    mr = sum(r for _, r in samples) / n
    var = sum((t - mt) ** 2 for t, _ in samples)
    return 60 * sum((t - mt) * (r - mr) for t, r in samples) / var if var else 0.0


def loadtest(url: str, zenoh: str, transport: str, args: list[str], out: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "phim", "loadtest", "--transport", transport, "--url", url]
    cmd += ["--zenoh-connect", zenoh, "--synthetic", "--no-progress", "--out", str(out), *args]
    return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def run(duration_s: float, factor: float, idle_s: float) -> dict:
    port, zport = free_port(), free_port()
    url, zenoh = f"http://127.0.0.1:{port}", f"tcp/127.0.0.1:{zport}"
    env = {"PHIM_PORT": str(port), "PHIM_ZENOH_LISTEN": zenoh, "PHIM_IDLE_TIMEOUT_S": str(idle_s)}
    tmp = Path(tempfile.mkdtemp(prefix="phim-soak-"))
    serve = [sys.executable, "-m", "phim", "serve"]
    with (tmp / "serve.log").open("w") as log:
        try:
            with spawned(serve, f"{url}/health/ready", env, log) as server:
                return soak(server.pid, url, zenoh, tmp, duration_s, factor, idle_s)
        except RuntimeError as e:  # it did not start: say why
            raise RuntimeError(f"{e}\n{(tmp / 'serve.log').read_text()[-2000:]}") from e


def measure_ceiling(url: str, zenoh: str, tmp: Path, min_answered: int = 20, tries: int = 5) -> float:
    """The server's closed-loop ceiling (sectors/s): a 5 s load test, twice as long each time it got fewer
    than `min_answered` answers (a busy machine's forwards are slow), `tries` times at most; then what the
    last one measured, if it got any answer at all."""
    duration_s = 5.0
    for _ in range(tries):
        probe = tmp / "capacity.json"
        args = ["--mode", "closed", "--vehicles", "4", "--duration", str(duration_s), "--timeout", "120"]
        loadtest(url, zenoh, "http", args, probe).wait()
        report = json.loads(probe.read_text())
        if report["answered"] >= min_answered:
            break
        duration_s *= 2
    if not report["answered"]:
        raise RuntimeError(f"the server answered no sector in {duration_s / 2:g} s: no ceiling to measure")
    return report["peak_achieved_sectors_per_s"]


def soak(pid: int, url: str, zenoh: str, tmp: Path, duration_s: float, factor: float, idle_s: float) -> dict:
    """Measure the ceiling, then load at `factor` times it over both transports, sampling the server."""
    capacity = measure_ceiling(url, zenoh, tmp)
    offered = factor * capacity  # sectors/s in all: vehicles at sensor rate, or slower where that is less
    vehicles = max(2, math.ceil(offered / SECTORS_PER_S))
    turns_per_s = max(0.01, offered / (vehicles * SECTORS_PER_TURN))  # 0.01: the load test's slowest
    offered = vehicles * SECTORS_PER_TURN * turns_per_s
    split = {"http": (vehicles + 1) // 2, "zenoh": vehicles // 2}
    samples: list[tuple[float, float, float, float]] = []  # seconds, RSS, heap in use, heap kept free (MB)
    done = threading.Event()

    def sample() -> None:
        t0 = time.monotonic()
        while not done.wait(1.0):
            samples.append((time.monotonic() - t0, rss_mb(pid), *heap_mb(url)))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    runs = {}
    for transport, n in split.items():
        args = ["--vehicles", str(n), "--duration", str(duration_s), "--warmup", "0"]
        args += ["--turns-per-s", f"{turns_per_s:.4f}", "--sectors-per-turn", str(SECTORS_PER_TURN)]
        # every sector gets its answer within the server's deadline plus a forward: the client waits long
        # enough for a busy machine to deliver it (a lost sector is one the server never answered)
        args += ["--timeout", "60", "--drain-timeout", "60"]
        args += ["--stream-prefix", f"soak-{transport}"]
        runs[transport] = (
            loadtest(url, zenoh, transport, args, tmp / f"{transport}.json"),
            tmp / f"{transport}.json",
        )
    reports = {}
    for transport, (proc, out) in runs.items():
        _, err = proc.communicate()
        reports[transport] = json.loads(out.read_text()) if out.exists() else {"error": err[-2000:]}
    done.set()
    evicted_by = time.monotonic() + idle_s + 3  # idle eviction: the timeout and the sweep's slack
    while (live := get_json(f"{url}/v1/streams")["live"]) and time.monotonic() < evicted_by:
        time.sleep(0.2)
    half = [s for s in samples if s[0] >= samples[-1][0] / 2] if samples else []
    none = (math.nan,) * 4
    first, last = (samples[0], samples[-1]) if samples else (none, none)
    return {
        "duration_s": duration_s,
        "capacity_sectors_per_s": capacity,
        "factor": factor,
        "offered_sectors_per_s": round(offered, 2),
        "vehicles": split,
        "reports": {
            t: {k: r.get(k) for k in ("sent", "answered", "ok", "errors", "lost", "errors_by_code")}
            for t, r in reports.items()
        },
        "rss_mb_start": first[1],
        "rss_mb_end": last[1],
        "rss_slope_mb_per_min": round(slope_mb_per_min([(t, r) for t, r, _, _ in half]), 2),
        # the RSS without what malloc keeps freed (the RSS where there is no glibc heap gauge)
        "rss_less_free_slope_mb_per_min": round(
            slope_mb_per_min([(t, r - (0.0 if math.isnan(f) else f)) for t, r, _, f in half]), 2
        ),
        "heap_mb_start": round(first[2], 1),
        "heap_mb_end": round(last[2], 1),
        "heap_free_mb_end": round(last[3], 1),
        "heap_slope_mb_per_min": round(slope_mb_per_min([(t, h) for t, _, h, _ in half]), 2),
        "live_streams_after_idle": live,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=600.0, help="Seconds of load.")
    parser.add_argument("--factor", type=float, default=2.0, help="Offered load over the measured ceiling.")
    parser.add_argument("--idle-timeout", type=float, default=5.0, help="The server's idle eviction (s).")
    parser.add_argument(
        "--max-rss-slope", type=float, default=20.0, help="RSS less malloc's free heap, MB/min (2nd half)."
    )
    parser.add_argument(
        "--max-heap-slope", type=float, default=5.0, help="Heap in use, MB/min over the second half."
    )
    parser.add_argument("--out", type=Path, help="Write the result as JSON.")
    a = parser.parse_args()
    result = run(a.duration, a.factor, a.idle_timeout)
    checks = {
        "every sector answered once": all(
            r.get("sent") and r["lost"] == 0 and r["sent"] == r["answered"]
            for r in result["reports"].values()
        ),
        "RSS flat (less malloc's free heap)": result["rss_less_free_slope_mb_per_min"] <= a.max_rss_slope,
        "no live streams after idle": result["live_streams_after_idle"] == 0,
    }
    if not math.isnan(result["heap_slope_mb_per_min"]):  # nan: no glibc, no heap gauge (said below)
        checks["heap in use flat"] = result["heap_slope_mb_per_min"] <= a.max_heap_slope
    result["checks"] = checks
    if a.out:
        a.out.write_text(json.dumps(result, indent=2))
    print("| transport | vehicles | sent | answered | ok | errors | lost |")
    print("|---|---|---|---|---|---|---|")
    for t, r in result["reports"].items():
        cells = [t, result["vehicles"][t], *(r[k] for k in ("sent", "answered", "ok", "errors", "lost"))]
        print("| " + " | ".join(str(c) for c in cells) + " |")
    r = result
    print(
        f"\nceiling {r['capacity_sectors_per_s']:.1f} sectors/s, offered x{a.factor:g} "
        f"({r['offered_sectors_per_s']:.1f} sectors/s) for {a.duration:g} s; "
        f"RSS {r['rss_mb_start']:.0f} -> {r['rss_mb_end']:.0f} MB, slope {r['rss_slope_mb_per_min']} MB/min "
        f"(second half), less malloc's free heap ({r['heap_free_mb_end']:.0f} MB at the end) "
        f"{r['rss_less_free_slope_mb_per_min']} MB/min; heap in use {r['heap_mb_start']:.0f} -> "
        f"{r['heap_mb_end']:.0f} MB, slope {r['heap_slope_mb_per_min']} MB/min; live streams after idle: "
        f"{r['live_streams_after_idle']}"
    )
    for name, ok in checks.items():
        print(f"{'PASS' if ok else 'FAIL'}: {name}")
    return 0 if all(checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
