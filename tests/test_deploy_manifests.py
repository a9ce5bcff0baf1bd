"""deploy/ without a cluster or a Docker engine: the Kubernetes manifests against the Kubernetes JSON schemas
(kubernetes-validate, strict: an unknown field fails), then what schemas cannot say (GPUs, probes on the
server's real health routes, grace periods that cover the drain, PHIM_* variables that are real settings,
ports on loopback only, the router without REST, the proxy's ring as deploy/nginx/phim.conf's), the Grafana
dashboard's metric names against a real server's /metrics, and the Prometheus scrape configs."""

from __future__ import annotations

import ast
import inspect
import json
import os
import re
from pathlib import Path
from typing import Any

import httpx
import kubernetes_validate
import pytest
import yaml
from conftest import REPO
from prometheus_client.parser import text_string_to_metric_families
from server_helpers import control_reply, serve

from server import metrics as server_metrics
from server.app import ROUTES
from server.settings import Settings

DEPLOY = REPO / "deploy"
K8S = DEPLOY / "k8s"
COMPOSE = DEPLOY / "docker-compose.yml"
NGINX_CONF = DEPLOY / "nginx" / "phim.conf"
PROMETHEUS = DEPLOY / "prometheus" / "prometheus.yml"
DASHBOARD = DEPLOY / "grafana" / "phim-dashboard.json"
GRAFANA_PROVISIONING = DEPLOY / "grafana" / "provisioning"
# the oldest release managed clusters still commonly run, and the newest the pinned kubernetes-validate ships
K8S_VERSIONS = ("1.33", "1.37")
DRAIN_S = Settings.model_fields["drain_timeout_s"].default
FORWARD_MARGIN_S = 10  # a forward still running when the drain ends, and the process's exit
SETTINGS_ENV = {f"PHIM_{name.upper()}" for name in Settings.model_fields}
ROUTE_PATHS = {fn.__name__: path for _, path, fn, _ in ROUTES}  # live, ready, metrics, ...
WORKER = "phim-worker"  # the StatefulSet, its headless Service and the compose services' prefix


# ------------------------------------------------------------------------------------------------ loading


def k8s_docs() -> list[tuple[str, dict[str, Any]]]:
    return [
        (path.name, doc)
        for path in sorted(K8S.glob("*.yaml"))
        if path.name != "kustomization.yaml"
        for doc in yaml.safe_load_all(path.read_text())
        if doc
    ]


def k8s(kind: str, name: str) -> dict[str, Any]:
    (doc,) = [d for _, d in k8s_docs() if d["kind"] == kind and d["metadata"]["name"] == name]
    return doc


def compose() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE.read_text())  # resolves the `<<: *worker` merge keys


def compose_workers() -> dict[str, dict[str, Any]]:
    services = compose()["services"]
    return {name: s for name, s in sorted(services.items()) if name.startswith(f"{WORKER}-")}


def worker_container() -> dict[str, Any]:
    (container,) = k8s("StatefulSet", WORKER)["spec"]["template"]["spec"]["containers"]
    return container


def env_of(container: dict[str, Any]) -> dict[str, Any]:
    """name -> value, or the valueFrom source."""
    return {e["name"]: e.get("value", e.get("valueFrom")) for e in container.get("env", [])}


def seconds(duration: str) -> float:
    m = re.fullmatch(r"(\d+)(s|m)", duration)
    assert m, duration
    return int(m[1]) * (60 if m[2] == "m" else 1)


def nginx_upstream(conf: str) -> list[str]:
    """The directives of the conf's one upstream block, whitespace collapsed, comments dropped."""
    conf = re.sub(r"#[^\n]*", "", conf)
    (block,) = re.findall(r"upstream\s+\w+\s*\{([^}]*)\}", conf)
    return [" ".join(d.split()) for d in block.split(";") if d.strip()]


def nginx_map(conf: str) -> str:
    """The `map ... $phim_stream { ... }` block (the hash key), whitespace collapsed, comments dropped."""
    conf = re.sub(r"#[^\n]*", "", conf)
    (block,) = re.findall(r"map\s+\S+\s+\$phim_stream\s*\{[^}]*\}", conf)
    return " ".join(block.split())


# ------------------------------------------------------------------------------ (a) the Kubernetes schemas


@pytest.mark.parametrize("version", K8S_VERSIONS)
def test_k8s_manifests_validate_strictly(version: str):
    docs = k8s_docs()
    assert {d["kind"] for _, d in docs} >= {"Namespace", "StatefulSet", "Service", "PodDisruptionBudget"}
    failures = []
    for name, doc in docs:
        try:
            kubernetes_validate.validate(doc, version, strict=True)
        except kubernetes_validate.ValidationError as e:
            failures.append(f"{name} {doc['kind']}/{doc['metadata']['name']}: {e.message}")
    assert not failures, "\n".join(failures)


def test_the_validation_catches_a_misspelled_field():
    sts = k8s("StatefulSet", WORKER)
    pod = sts["spec"]["template"]["spec"]
    pod["terminationGracePeriodSecond"] = pod.pop("terminationGracePeriodSeconds")  # a lax check ignores it
    with pytest.raises(kubernetes_validate.ValidationError, match="terminationGracePeriodSecond"):
        kubernetes_validate.validate(sts, K8S_VERSIONS[-1], strict=True)


def test_kustomization_lists_every_manifest():
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    listed = kustomization["resources"]
    assert sorted(listed) == sorted(p.name for p in K8S.glob("*.yaml") if p.name != "kustomization.yaml")
    namespaces = {d["metadata"].get("namespace") for _, d in k8s_docs() if d["kind"] != "Namespace"}
    assert namespaces == {k8s("Namespace", "phim")["metadata"]["name"]}  # all in it, none in `default`


# ------------------------------------------------------------------------------ (b) the workloads


def test_workers_get_a_gpu_each_and_tolerate_gpu_nodes():
    pod = k8s("StatefulSet", WORKER)["spec"]["template"]["spec"]
    resources = worker_container()["resources"]
    assert int(resources["limits"]["nvidia.com/gpu"]) == 1
    assert int(resources["requests"].get("nvidia.com/gpu", 1)) == 1  # requests must equal limits for GPUs
    assert "memory" in resources["limits"] and "cpu" in resources["requests"]
    assert any(
        t["key"] == "nvidia.com/gpu" and t["effect"] == "NoSchedule" and t["operator"] == "Exists"
        for t in pod["tolerations"]
    )
    env = env_of(worker_container())
    assert env["PHIM_DEVICE"].startswith("cuda")
    for name, service in compose_workers().items():
        (device,) = service["deploy"]["resources"]["reservations"]["devices"]
        assert device["driver"] == "nvidia" and "gpu" in device["capabilities"], name
        assert service["environment"]["PHIM_DEVICE"].startswith("cuda"), name
    ids = [
        s["deploy"]["resources"]["reservations"]["devices"][0]["device_ids"]
        for s in compose_workers().values()
    ]
    assert len({tuple(i) for i in ids}) == len(ids) == 3  # one GPU each, not all on GPU 0


def test_worker_probes_ask_the_real_health_routes():
    container = worker_container()
    (port,) = container["ports"]
    assert int(env_of(container)["PHIM_PORT"]) == port["containerPort"]
    probes = {kind: container[kind] for kind in ("startupProbe", "readinessProbe", "livenessProbe")}
    for probe in probes.values():
        assert probe["httpGet"]["port"] in (port["name"], port["containerPort"])
    assert probes["readinessProbe"]["httpGet"]["path"] == ROUTE_PATHS["ready"]
    assert probes["livenessProbe"]["httpGet"]["path"] == ROUTE_PATHS["live"]
    startup = probes["startupProbe"]
    assert startup["httpGet"]["path"] in (ROUTE_PATHS["ready"], ROUTE_PATHS["live"])
    # warm-up, and with --engine graph one compilation per batch bucket, before the liveness probe may kill it
    assert startup.get("periodSeconds", 10) * startup.get("failureThreshold", 3) >= 300


def test_grace_periods_cover_the_drain():
    pod = k8s("StatefulSet", WORKER)["spec"]["template"]["spec"]
    pre_stop = worker_container().get("lifecycle", {}).get("preStop", {}).get("sleep", {}).get("seconds", 0)
    assert pod["terminationGracePeriodSeconds"] >= pre_stop + DRAIN_S + FORWARD_MARGIN_S
    for name, service in compose_workers().items():
        assert seconds(service["stop_grace_period"]) >= DRAIN_S + FORWARD_MARGIN_S, name


def test_worker_pods_run_as_non_root_with_the_tokens_from_a_secret():
    pod = k8s("StatefulSet", WORKER)["spec"]["template"]["spec"]
    container = worker_container()
    assert pod["securityContext"]["runAsNonRoot"] is True and pod["securityContext"]["runAsUser"] != 0
    assert container["securityContext"]["allowPrivilegeEscalation"] is False
    tokens = Path(env_of(container)["PHIM_AUTH_TOKENS"])
    (mount,) = [m for m in container["volumeMounts"] if tokens.parent == Path(m["mountPath"])]
    (volume,) = [v for v in pod["volumes"] if v["name"] == mount["name"]]
    assert "secret" in volume and "subPath" not in mount  # a subPath mount would never see a rotated token
    assert "PHIM_INSECURE" not in env_of(container)


def test_worker_identity_and_the_headless_service():
    sts = k8s("StatefulSet", WORKER)
    assert env_of(worker_container())["PHIM_WORKER_ID"] == {"fieldRef": {"fieldPath": "metadata.name"}}
    service = k8s("Service", sts["spec"]["serviceName"])
    assert service["spec"]["clusterIP"] == "None"
    labels = sts["spec"]["template"]["metadata"]["labels"]
    assert service["spec"]["selector"].items() <= labels.items()
    assert k8s("PodDisruptionBudget", WORKER)["spec"]["selector"]["matchLabels"].items() <= labels.items()
    for name, service in compose_workers().items():
        assert service["environment"]["PHIM_WORKER_ID"] == name  # unique, and the proxy's upstream name


def fleet_env(env: dict[str, Any]) -> None:
    assert env["PHIM_ZENOH_MODE"] == "client" and env["PHIM_ZENOH_LISTEN"] == ""
    assert env["PHIM_ZENOH_CONNECT"].startswith("tcp/zenoh-router:")
    assert env["PHIM_ZENOH_SHARED_KEYS"] in ("0", "false")  # each worker answers only its own keys
    assert env["PHIM_HOST"] == "0.0.0.0" and env["PHIM_PUBLIC_METRICS"] in ("1", "true")


def test_every_phim_variable_is_a_real_setting_with_a_valid_value(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    tokens = tmp_path / "tokens"
    tokens.write_text("")
    k8s_env = env_of(worker_container()) | {"PHIM_WORKER_ID": f"{WORKER}-0", "PHIM_AUTH_TOKENS": str(tokens)}
    envs = {f"compose {n}": s.get("environment", {}) for n, s in compose()["services"].items()}
    envs["k8s StatefulSet"] = k8s_env
    for where, env in envs.items():
        phim = {k: str(v) for k, v in env.items() if k.startswith("PHIM_")}
        assert set(phim) <= SETTINGS_ENV, f"{where}: not settings: {sorted(set(phim) - SETTINGS_ENV)}"
        if phim:  # the values parse as `phim serve` would read them
            for key in [k for k in os.environ if k.startswith("PHIM_")]:
                monkeypatch.delenv(key)
            for key, value in phim.items():
                monkeypatch.setenv(key, value)
            Settings()
    fleet_env(k8s_env)
    for env in (s["environment"] for s in compose_workers().values()):
        fleet_env(env)


def test_compose_publishes_on_loopback_only():
    services = compose()["services"]
    published = [(n, str(p)) for n, s in services.items() for p in s.get("ports", [])]
    assert published and all(p.startswith("127.0.0.1:") for _, p in published), published
    assert not any(s.get("network_mode") == "host" for s in services.values())
    assert not any("ports" in s for s in compose_workers().values())  # reached through the proxy only


def router_is_rest_free(image: str, args: list[str], ports: list[str]) -> None:
    if image.startswith("eclipse/zenoh:"):
        # zenohd 1.1.0 and later load the REST plugin only with --rest-http-port or a config's plugins.rest
        major, minor = (int(x) for x in image.split(":")[1].split(".")[:2])
        assert (major, minor) >= (1, 1), image
        assert not any(a.startswith(("--rest-http-port", "-c", "--config", "--cfg")) for a in args), args
    else:  # the PHiM image's `phim router`: eclipse-zenoh in router mode, no plugins at all
        assert args[:2] == ["phim", "router"], args
    assert not any(str(p).split(":")[-1] in ("8000", "8000/tcp") for p in ports), ports


def test_the_zenoh_routers_run_without_rest():
    router = compose()["services"]["zenoh-router"]
    router_is_rest_free(router["image"], router.get("command", []), router.get("ports", []))
    pod = k8s("Deployment", "zenoh-router")["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    ports = [str(p["containerPort"]) for p in container["ports"]]
    router_is_rest_free(container["image"], container.get("command", []) + container.get("args", []), ports)
    service_ports = [str(p["port"]) for p in k8s("Service", "zenoh-router")["spec"]["ports"]]
    assert "8000" not in service_ports


def test_the_proxies_hash_streams_as_phim_conf():
    k8s_conf = k8s("ConfigMap", "phim-proxy")["data"]["nginx.conf"]
    sts = k8s("StatefulSet", WORKER)
    ns, port = sts["metadata"]["namespace"], worker_container()["ports"][0]["containerPort"]
    servers = [d for d in nginx_upstream(k8s_conf) if d.startswith("server ")]
    # one per replica, by the pods' stable names (resolve: nginx follows their addresses)
    want = [
        f"server {WORKER}-{i}.{sts['spec']['serviceName']}.{ns}.svc.cluster.local:{port} resolve"
        for i in range(sts["spec"]["replicas"])
    ]
    assert servers == want
    compose_servers = [f"server {name}:8080" for name in compose_workers()]
    if NGINX_CONF.exists():  # written beside this test; the compose proxy mounts it
        shipped = NGINX_CONF.read_text()
        hashes = [[d for d in nginx_upstream(c) if d.startswith("hash ")] for c in (k8s_conf, shipped)]
        assert hashes[0] == hashes[1] == ["hash $phim_stream consistent"]
        assert nginx_map(k8s_conf) == nginx_map(shipped)
        assert sorted(d for d in nginx_upstream(shipped) if d.startswith("server ")) == compose_servers
    proxy = compose()["services"]["proxy"]
    assert f"./nginx/{NGINX_CONF.name}:/etc/nginx/nginx.conf:ro" in proxy["volumes"]
    (container,) = k8s("Deployment", "phim-proxy")["spec"]["template"]["spec"]["containers"]
    # `resolve` in an upstream: nginx 1.27.3 and later (a tag without a patch level is that branch's newest)
    version = re.fullmatch(r"nginx:(\d+)\.(\d+)(?:\.(\d+))?(?:-\w+)?", container["image"])
    assert version, container["image"]
    major, minor, patch = (int(x or 99) for x in version.groups())
    assert (major, minor, patch) >= (1, 27, 3), container["image"]


# ------------------------------------------------------------------------------ (c) the Grafana dashboard


PROMQL_WORDS = {"by", "without", "on", "ignoring", "group_left", "group_right", "bool", "and", "or", "unless"}


def promql_metrics(expr: str) -> set[str]:
    """The metric names a PromQL expression reads: identifiers outside label matchers, ranges, strings and
    by/without lists that are neither functions nor keywords."""
    expr = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)
    expr = re.sub(r"\{[^}]*\}|\[[^\]]*\]", " ", expr)
    expr = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", " ", expr)
    names = set()
    for m in re.finditer(r"(?<![\w.$])[A-Za-z_:][\w:]*", expr):
        if m[0] not in PROMQL_WORDS and not expr[m.end() :].lstrip().startswith("("):
            names.add(m[0])
    return names


def test_promql_metrics_finds_names_and_only_names():
    expr = (
        'histogram_quantile(0.99, sum by (worker, le) (rate(phm_x_bucket{worker=~"$w"}[$__rate_interval])))'
    )
    assert promql_metrics(expr) == {"phm_x_bucket"}
    assert promql_metrics("a_total / on (job) group_left b + max(c) and d") == {"a_total", "b", "c", "d"}


def dashboard_queries(dashboard: dict[str, Any]) -> list[str]:
    exprs = [t["expr"] for p in dashboard["panels"] for t in p.get("targets", [])]
    for var in dashboard["templating"]["list"]:
        if var["type"] == "query":  # label_values(metric, label) reads `metric`
            query = var["query"]["query"] if isinstance(var["query"], dict) else var["query"]
            exprs.append(re.sub(r"^label_values\((\w+),\s*\w+\)$", r"\1", query))
    return exprs


def exported_names(text: str) -> set[str]:
    """The series names an exposition gives Prometheus, with those its families would have once labelled:
    a labelled counter with no series yet is only its HELP and TYPE lines. A counter or histogram family's
    own name (the parser's, without `_total`) is no series."""
    suffixes = {
        "counter": ("_total",),
        "histogram": ("_bucket", "_sum", "_count"),
        "summary": ("_sum", "_count"),
    }
    names = set()
    for family in text_string_to_metric_families(text):
        names |= {s.name for s in family.samples}
        names |= {family.name + suffix for suffix in suffixes.get(family.type, ("",))}
    return names


def gpu_metric_names() -> set[str]:
    # The GPU gauges exist only on CUDA (GpuCollector registers when the model loads there); no GPU here, so
    # their names come from the collector's source: the string constants that name phim_gpu_* families.
    tree = ast.parse(inspect.getsource(server_metrics.GpuCollector))
    names = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    return {n for n in names if re.fullmatch(r"phim_gpu_\w+", n)}


def test_dashboard_reads_only_metrics_a_server_exports():
    dashboard = json.loads(DASHBOARD.read_text())
    assert dashboard["uid"] and dashboard["title"]
    ids = [p["id"] for p in dashboard["panels"]]
    assert len(ids) == len(set(ids))
    wanted = set().union(*(promql_metrics(e) for e in dashboard_queries(dashboard)))
    core = {"phim_sectors_total", "phim_sector_latency_seconds_bucket", "phim_model_latency_seconds_bucket"}
    assert wanted >= core | {"phim_queued_sectors", "phim_live_streams", "phim_gpu_memory_allocated_bytes"}
    with serve(None) as server:
        control_reply(server.url, "dashboard-1")  # the labelled phim_sectors_total series appear
        exposition = httpx.get(f"{server.url}{ROUTE_PATHS['metrics']}", timeout=10).text
    gpu = gpu_metric_names()
    assert {"phim_gpu_memory_allocated_bytes", "phim_gpu_memory_total_bytes"} <= gpu
    exported = exported_names(exposition) | gpu
    assert not wanted - exported, f"not exported by the server: {sorted(wanted - exported)}"


def test_dashboard_groups_by_labels_that_exist():
    dashboard = json.loads(DASHBOARD.read_text())
    text = json.dumps(dashboard)
    used = set(re.findall(r"\b(?:by|without) \(([^)]*)\)", text))
    used = {label.strip() for group in used for label in group.split(",")}
    used |= set(re.findall(r"\{\{(\w+)\}\}", text))  # legends
    server_labels = {"transport", "outcome", "device", "le", *server_metrics.BUILD_LABELS}
    assert used <= server_labels | {"worker", "instance", "job"}, used  # worker: set by both scrape configs


# ------------------------------------------------------------------------------ (d) Prometheus and Grafana


def sets_worker_label(job: dict[str, Any]) -> bool:
    return any(r.get("target_label") == "worker" for r in job.get("relabel_configs", []))


def test_compose_prometheus_scrapes_every_worker_directly():
    (job,) = yaml.safe_load(PROMETHEUS.read_text())["scrape_configs"]
    assert job.get("metrics_path", "/metrics") == ROUTE_PATHS["metrics"]
    targets = [t for c in job["static_configs"] for t in c["targets"]]
    assert sorted(targets) == [f"{name}:8080" for name in compose_workers()]
    assert sets_worker_label(job)
    relabel = job["relabel_configs"][0]
    assert re.fullmatch(relabel["regex"], targets[0])[1] == f"{WORKER}-0"  # worker="phim-worker-0"
    volumes = compose()["services"]["prometheus"]["volumes"]
    assert f"./prometheus/{PROMETHEUS.name}:/etc/prometheus/prometheus.yml:ro" in volumes


def test_k8s_prometheus_finds_the_worker_pods():
    config = yaml.safe_load(k8s("ConfigMap", "phim-prometheus")["data"]["prometheus.yml"])
    (job,) = config["scrape_configs"]
    assert job.get("metrics_path", "/metrics") == ROUTE_PATHS["metrics"]
    (sd,) = job["kubernetes_sd_configs"]
    sts = k8s("StatefulSet", WORKER)
    assert sd["role"] == "pod" and sd["namespaces"]["names"] == [sts["metadata"]["namespace"]]
    keep = {r["source_labels"][0]: r["regex"] for r in job["relabel_configs"] if r.get("action") == "keep"}
    label = sts["spec"]["template"]["metadata"]["labels"]["app.kubernetes.io/name"]
    assert keep["__meta_kubernetes_pod_label_app_kubernetes_io_name"] == label
    assert keep["__meta_kubernetes_pod_container_port_name"] == worker_container()["ports"][0]["name"]
    assert sets_worker_label(job)


def test_grafana_is_provisioned_with_prometheus_and_the_dashboard():
    grafana = compose()["services"]["grafana"]
    (source,) = yaml.safe_load((GRAFANA_PROVISIONING / "datasources" / "prometheus.yml").read_text())[
        "datasources"
    ]
    assert source["type"] == "prometheus" and source["url"] == "http://prometheus:9090"
    (provider,) = yaml.safe_load((GRAFANA_PROVISIONING / "dashboards" / "phim.yml").read_text())["providers"]
    mounts = dict(v.rsplit(":", 1)[0].split(":", 1) for v in grafana["volumes"])
    assert mounts[f"./grafana/{DASHBOARD.name}"] == f"{provider['options']['path']}/{DASHBOARD.name}"
    assert mounts["./grafana/provisioning"] == "/etc/grafana/provisioning"
    assert "${GRAFANA_ADMIN_PASSWORD" in grafana["environment"]["GF_SECURITY_ADMIN_PASSWORD"]
