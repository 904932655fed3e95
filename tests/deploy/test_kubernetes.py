"""The Kubernetes manifests (deploy/k8s), checked offline: every resource against the Kubernetes
OpenAPI schemas (kubernetes-validate, strict), and what a schema cannot see: the kustomizations
name files that exist, the Service/PDB/HPA point at the Deployment, the settings are settings of
``collider serve``, the HPA's metric is one the service exports and the adapter rule serves, the
grace period matches compose, the CPU and GPU Deployments stay in step; and, on the rendered
manifests (a small reader of the kustomizations, checked against ``kubectl kustomize`` where it is
installed): each pod is scraped through exactly one Service, the HPA alone sets the replica count,
no placeholder secret reaches a pod (issue 21, items 6-9)."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import pytest
import yaml

from .conftest import REPO

K8S = REPO / "deploy" / "k8s"
OVERLAYS = ("cpu", "gpu")
#: The oldest Kubernetes these manifests claim (docker/README.md): the preStop `sleep` action.
MIN_VERSION = "1.30"

kubernetes_validate = pytest.importorskip(
    "kubernetes_validate", reason="kubernetes-validate is not installed (the dev extra has it)")


def documents(path: Path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d]


def kustomization_files(folder: Path) -> list[Path]:
    """Every resource file a kustomization pulls in, following folders to their kustomization."""
    found = []
    for entry in documents(folder / "kustomization.yaml")[0]["resources"]:
        target = (folder / entry).resolve()
        assert target.exists(), f"{folder / 'kustomization.yaml'}: {entry} does not exist"
        found += kustomization_files(target) if target.is_dir() else [target]
    return found


def common_labels(folder: Path) -> dict[str, str]:
    """The ``labels`` pairs a kustomization and the ones it includes put on every resource's
    metadata (``includeSelectors``/``includeTemplates`` are not used here: metadata only)."""
    kustomization = documents(folder / "kustomization.yaml")[0]
    labels = {}
    for entry in kustomization.get("resources", []):
        if (folder / entry).is_dir():
            labels.update(common_labels((folder / entry).resolve()))
    for group in kustomization.get("labels", []):
        assert not group.get("includeSelectors") and not group.get("includeTemplates")
        labels.update(group["pairs"])
    return labels


def render(folder: Path) -> list[dict]:
    """``kubectl kustomize folder``, for what these kustomizations use (resources, labels)."""
    kustomization = documents(folder / "kustomization.yaml")[0]
    assert set(kustomization) <= {"apiVersion", "kind", "resources", "labels"}, \
        f"{folder}: the reader knows resources and labels only"
    rendered = []
    for entry in kustomization["resources"]:
        target = (folder / entry).resolve()
        rendered += render(target) if target.is_dir() else copy.deepcopy(documents(target))
    for group in kustomization.get("labels", []):
        for doc in rendered:
            doc["metadata"].setdefault("labels", {}).update(group["pairs"])
    return rendered


def resources(overlay: str) -> dict[tuple[str, str], dict]:
    """What ``kubectl apply -k overlays/<overlay>`` would create, by (kind, name)."""
    found = {}
    for doc in render(K8S / "overlays" / overlay):
        key = (doc["kind"], doc["metadata"]["name"])
        assert key not in found, f"{key} twice"
        found[key] = doc
    return found


#: Every kustomization a user applies (docker/README.md, "A cluster").
KUSTOMIZATIONS = ("overlays/cpu", "overlays/gpu", "monitoring", "router")


def all_core_resources() -> list[tuple[Path, dict]]:
    paths = sorted(set(kustomization_files(K8S / "overlays" / "cpu"))
                   | set(kustomization_files(K8S / "overlays" / "gpu"))
                   | set(kustomization_files(K8S / "router"))
                   | {K8S / "models-loader.yaml"})
    return [(p, d) for p in paths for d in documents(p)]


@pytest.mark.parametrize("version", [MIN_VERSION, None])
def test_every_resource_passes_the_kubernetes_schema(version):
    version = version or kubernetes_validate.latest_version()
    checked = 0
    for path, doc in all_core_resources():
        try:
            kubernetes_validate.validate(doc, version, strict=True)
        except kubernetes_validate.ValidationError as exc:
            raise AssertionError(f"{path.relative_to(REPO)}: {exc.message} at {exc.path}") from None
        checked += 1
    assert checked >= 10


def test_the_schema_check_is_not_vacuous():
    deployment = resources("cpu")[("Deployment", "collider")]
    broken = copy.deepcopy(deployment)
    broken["spec"]["template"]["spec"]["containers"][0]["readinessProbe"]["httpGet"]["paht"] = "/"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(broken, kubernetes_validate.latest_version(), strict=True)


def container(overlay: str) -> dict:
    (c,) = resources(overlay)[("Deployment", "collider")]["spec"]["template"]["spec"]["containers"]
    return c


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_deployment_is_wired_to_the_other_resources(overlay):
    found = resources(overlay)
    deployment = found[("Deployment", "collider")]
    pod_labels = deployment["spec"]["template"]["metadata"]["labels"]
    assert deployment["spec"]["selector"]["matchLabels"].items() <= pod_labels.items()
    for kind, name in [("Service", "collider"), ("Service", "collider-replicas")]:
        assert found[(kind, name)]["spec"]["selector"].items() <= pod_labels.items()
    assert found[("PodDisruptionBudget", "collider")]["spec"]["selector"]["matchLabels"].items() \
        <= pod_labels.items()
    target = found[("HorizontalPodAutoscaler", "collider")]["spec"]["scaleTargetRef"]
    assert (target["kind"], target["name"]) == ("Deployment", "collider")

    pod = deployment["spec"]["template"]["spec"]
    c = container(overlay)
    port_names = {p["name"] for p in c["ports"]}
    probes = {k: c[k]["httpGet"] for k in ("startupProbe", "livenessProbe", "readinessProbe")}
    assert probes["livenessProbe"]["path"] == "/livez" and probes["readinessProbe"]["path"] == "/readyz"
    assert all(p["port"] in port_names for p in probes.values())
    for ref in c["envFrom"]:
        assert ("ConfigMap", ref["configMapRef"]["name"]) in found
    # The Secret is made by hand with the command in base/kustomization.yaml (issue 21, item 8).
    made = (K8S / "base" / "kustomization.yaml").read_text()
    for env in c["env"]:
        if "valueFrom" in env:
            ref = env["valueFrom"]["secretKeyRef"]
            assert f"create secret generic {ref['name']}" in made
            assert f"--from-literal={ref['key']}=" in made
    claims = [v["persistentVolumeClaim"] for v in pod["volumes"] if "persistentVolumeClaim" in v]
    assert claims and all(("PersistentVolumeClaim", c_["claimName"]) in found for c_ in claims)
    assert all(c_["readOnly"] for c_ in claims)
    assert {m["mountPath"]: m.get("readOnly", False) for m in c["volumeMounts"]}["/models"] is True
    assert c["resources"]["limits"]["cpu"] and c["resources"]["limits"]["memory"]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_pods_run_as_the_images_non_root_user_on_a_read_only_root(overlay):
    pod = resources(overlay)[("Deployment", "collider")]["spec"]["template"]["spec"]
    dockerfile = (REPO / "docker" / "Dockerfile").read_text()
    image_uid = int(re.findall(r"^USER (\d+)", dockerfile, re.MULTILINE)[-1])
    assert pod["securityContext"]["runAsNonRoot"] is True
    assert pod["securityContext"]["runAsUser"] == image_uid
    security = container(overlay)["securityContext"]
    assert security["readOnlyRootFilesystem"] is True and security["allowPrivilegeEscalation"] is False
    assert security["capabilities"]["drop"] == ["ALL"]
    # The only writable place is an emptyDir at /tmp (the images' HOME and working folder).
    writable = [m["mountPath"] for m in container(overlay)["volumeMounts"] if not m.get("readOnly")]
    assert writable == ["/tmp"]


def test_settings_are_settings_of_collider_serve():
    from collider_server.service.settings import ServiceSettings

    fields = {f"COLLIDER_{name.upper()}" for name in ServiceSettings.model_fields}
    config = resources("cpu")[("ConfigMap", "collider-config")]["data"]
    assert set(config) <= fields, set(config) - fields
    for overlay in OVERLAYS:
        names = {e["name"] for e in container(overlay)["env"]}
        assert names <= fields, names - fields
        assert not names & set(config), "a setting both in the ConfigMap and the Deployment"


def test_cpu_and_gpu_deployments_differ_only_in_image_device_resources_and_placement():
    def normalised(overlay):
        d = copy.deepcopy(resources(overlay)[("Deployment", "collider")])
        pod = d["spec"]["template"]["spec"]
        pod.pop("tolerations", None)
        (c,) = pod["containers"]
        c.pop("image"), c.pop("resources")
        c["env"] = [e for e in c["env"] if e["name"] not in ("COLLIDER_DEVICE",
                                                             "COLLIDER_COMPUTE_THREADS")]
        return d

    assert normalised("cpu") == normalised("gpu")
    assert container("gpu")["resources"]["limits"]["nvidia.com/gpu"] == 1
    assert container("gpu")["image"].endswith(":cuda") and container("cpu")["image"].endswith(":cpu")


def seconds(value: str) -> int:
    number, unit = re.fullmatch(r"(\d+)(s|m)", value).groups()
    return int(number) * (60 if unit == "m" else 1)


def test_grace_periods_cover_the_servers_bounded_drain():
    """SIGKILL must never cut the drain short: compose's stop_grace_period and the pods'
    terminationGracePeriodSeconds exceed the drain (COLLIDER_GRACEFUL_SHUTDOWN_S, one value in the
    images, compose and the ConfigMap) plus the preStop pause, with 5 s to spare."""
    compose = yaml.safe_load((REPO / "docker" / "compose.yaml").read_text())["services"]["collider"]
    config = resources("cpu")[("ConfigMap", "collider-config")]["data"]
    dockerfile = (REPO / "docker" / "Dockerfile").read_text()
    drains = {float(compose["environment"]["COLLIDER_GRACEFUL_SHUTDOWN_S"]),
              float(config["COLLIDER_GRACEFUL_SHUTDOWN_S"]),
              *map(float, re.findall(r"COLLIDER_GRACEFUL_SHUTDOWN_S=(\S+)", dockerfile))}
    assert len(drains) == 1, f"different drains: {drains}"
    (drain,) = drains
    assert seconds(compose["stop_grace_period"]) >= drain + 5
    for overlay in OVERLAYS:
        pod = resources(overlay)[("Deployment", "collider")]["spec"]["template"]["spec"]
        pause = container(overlay)["lifecycle"]["preStop"]["sleep"]["seconds"]
        assert pod["terminationGracePeriodSeconds"] >= pause + drain + 5


def test_hpa_scales_on_the_queue_metric_the_adapter_serves():
    hpa = resources("cpu")[("HorizontalPodAutoscaler", "collider")]
    (metric,) = hpa["spec"]["metrics"]
    assert metric["type"] == "Pods" and metric["pods"]["metric"]["name"] == "collider_queue_points"
    adapter = documents(K8S / "monitoring" / "prometheus-adapter-values.yaml")[0]
    served = {rule["name"]["as"] for rule in adapter["rules"]["custom"]}
    assert "collider_queue_points" in served
    monitoring = [d for p in kustomization_files(K8S / "monitoring") for d in documents(p)]
    monitor = next(d for d in monitoring if d["kind"] == "ServiceMonitor")
    assert monitor["spec"]["endpoints"][0]["path"] == "/metrics"
    assert monitor["spec"]["selector"]["matchLabels"].items() <= \
        resources("cpu")[("Service", "collider-replicas")]["metadata"]["labels"].items()


def test_the_service_exports_the_metrics_the_manifests_use():
    from collider_server.service.metrics import ServiceMetrics

    exported = ServiceMetrics().render()[0].decode()
    if "collider_queue_points" not in exported:
        pytest.skip("collider_queue_points is not exported yet (issue 10 adds it)")
    rules = (K8S / "monitoring" / "alerts.yaml").read_text()
    for name in set(re.findall(r"\b(collider_[a-z_]+?)(?:_total|_bucket)?\b", rules)):
        types = (f"# TYPE {name} ", f"# TYPE {name}_total counter")  # counters: either spelling
        assert any(t in exported for t in types), f"alerts.yaml uses {name}, which /metrics lacks"


def test_router_runs_the_compose_nginx_file_against_the_headless_service():
    router = {(d["kind"], d["metadata"]["name"]): d
              for p in kustomization_files(K8S / "router") for d in documents(p)}
    deployment = router[("Deployment", "collider-router")]
    pod = deployment["spec"]["template"]["spec"]
    (nginx,) = pod["containers"]
    env = {e["name"]: e["value"] for e in nginx["env"]}
    template = (REPO / "docker" / "nginx" / "collider.conf.template").read_text()
    assert set(re.findall(r"\$\{(\w+)\}", template)) <= set(env)
    assert env["NGINX_LISTEN"] == str(nginx["ports"][0]["containerPort"])
    headless = resources("cpu")[("Service", "collider-replicas")]
    port = headless["spec"]["ports"][0]["port"]
    assert f"server {headless['metadata']['name']}." in env["COLLIDER_UPSTREAMS"]
    assert f":{port} resolve" in env["COLLIDER_UPSTREAMS"]
    mounts = {m["mountPath"]: m["name"] for m in nginx["volumeMounts"]}
    volumes = {v["name"]: v for v in pod["volumes"]}
    template_volume = volumes[mounts["/etc/nginx/templates"]]
    # The ConfigMap that kustomization.yaml tells the reader to create from the template file.
    name = template_volume["configMap"]["name"]
    assert f"kubectl create configmap {name}" in (K8S / "router" / "kustomization.yaml").read_text()
    assert router[("Service", "collider-router")]["spec"]["selector"].items() <= \
        deployment["spec"]["template"]["metadata"]["labels"].items()
    assert pod["securityContext"]["runAsNonRoot"] and nginx["securityContext"]["readOnlyRootFilesystem"]


# -- the rendered manifests (issue 21, items 6-9) ----------------------------------------------


@pytest.mark.parametrize("folder", KUSTOMIZATIONS)
def test_the_reader_renders_as_kubectl_kustomize(folder):
    import shutil
    import subprocess

    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl is not installed: the reader alone renders the manifests")
    result = subprocess.run([kubectl, "kustomize", str(K8S / folder)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    key = lambda d: (d["kind"], d["metadata"]["name"])
    assert sorted([d for d in yaml.safe_load_all(result.stdout) if d], key=key) == \
        sorted(render(K8S / folder), key=key)


def cluster(overlay: str) -> list[dict]:
    """Everything the README applies for one variant: the overlay, monitoring and the router."""
    return render(K8S / "overlays" / overlay) + render(K8S / "monitoring") + render(K8S / "router")


def selects(selector: dict, labels: dict) -> bool:
    return bool(selector) and selector.items() <= labels.items()


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_each_collider_pod_is_scraped_through_exactly_one_service(overlay):
    """A pod behind two monitored Services is scraped twice: the adapter's sum by (pod) doubles
    the queue depth, the HPA scales at half its target and the alerts fire at half theirs."""
    docs = cluster(overlay)
    services = [d for d in docs if d["kind"] == "Service"]
    monitors = [d for d in docs if d["kind"] == "ServiceMonitor"]
    assert monitors
    for deployment in (d for d in docs if d["kind"] == "Deployment"):
        pod = deployment["spec"]["template"]["metadata"]["labels"]
        ports = {p["name"] for c in deployment["spec"]["template"]["spec"]["containers"]
                 for p in c.get("ports", [])}
        scraped = [(m["metadata"]["name"], s["metadata"]["name"]) for m in monitors
                   for s in services
                   if selects(m["spec"]["selector"]["matchLabels"], s["metadata"]["labels"])
                   and selects(s["spec"]["selector"], pod)
                   and any(e["port"] in {p["name"] for p in s["spec"]["ports"]} for e in
                           m["spec"]["endpoints"])]
        if deployment["metadata"]["name"] == "collider":
            assert scraped == [("collider", "collider-replicas")], scraped
            assert all(e["port"] in ports for m in monitors for e in m["spec"]["endpoints"])
        else:  # the router (nginx) has no /metrics of its own
            assert scraped == [], (deployment["metadata"]["name"], scraped)


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_no_deployment_sets_replicas_where_an_hpa_scales_it(overlay):
    """``kubectl apply -k`` would reset the HPA's count to the manifest's every time."""
    docs = cluster(overlay)
    targets = {(h["spec"]["scaleTargetRef"]["kind"], h["spec"]["scaleTargetRef"]["name"])
               for h in docs if h["kind"] == "HorizontalPodAutoscaler"}
    assert ("Deployment", "collider") in targets
    for doc in docs:
        if (doc["kind"], doc["metadata"]["name"]) in targets:
            assert "replicas" not in doc["spec"], f"{doc['metadata']['name']} sets replicas"


def secret_values(doc: dict) -> list[str]:
    import base64

    return [*doc.get("stringData", {}).values(),
            *(base64.b64decode(v).decode() for v in doc.get("data", {}).values())]


def test_no_placeholder_secret_reaches_a_pod():
    """No rendered Secret, ConfigMap or env value holds a token; the Secret is made by hand, and
    the service refuses a placeholder token (tests/service/test_operations.py)."""
    from collider_server.service.settings import PLACEHOLDER_TOKENS

    everything = [d for overlay in OVERLAYS for d in cluster(overlay)] + \
        documents(K8S / "models-loader.yaml")
    assert not [d for d in everything if d["kind"] == "Secret"], "a Secret ships with the files"
    for doc in everything:
        values = secret_values(doc) if doc["kind"] == "Secret" else \
            [str(v) for v in doc.get("data", {}).values()] if doc["kind"] == "ConfigMap" else []
        pod = doc.get("spec", {}).get("template", {}).get("spec") or doc.get("spec", {})
        for c in pod.get("containers", []):
            values += [str(e.get("value", "")) for e in c.get("env", [])]
        assert not {v.strip().lower() for v in values} & PLACEHOLDER_TOKENS, doc["metadata"]
    for overlay in OVERLAYS:
        env = {e["name"]: e for e in container(overlay)["env"]}
        token = env["COLLIDER_TOKEN"]["valueFrom"]["secretKeyRef"]
        assert not token.get("optional"), "without its token a replica must not start"
        admin = env["COLLIDER_ADMIN_TOKEN"]["valueFrom"]["secretKeyRef"]
        assert admin["optional"] is True  # no admin-token key: admin routes off
    # The documented command makes the query token only: admin stays off unless asked for.
    made = (K8S / "base" / "kustomization.yaml").read_text()
    command = re.search(r"kubectl create secret generic collider-tokens.*", made).group(0)
    assert "--from-literal=token=$(openssl rand" in command and "admin-token" not in command


def test_monitoring_is_found_by_a_stock_kube_prometheus_stack_and_the_adapter_finds_prometheus():
    monitoring = render(K8S / "monitoring")
    for doc in monitoring:
        assert doc["metadata"]["labels"].get("release"), f"{doc['kind']} lacks the release label"
    adapter = documents(K8S / "monitoring" / "prometheus-adapter-values.yaml")[0]
    assert adapter["prometheus"]["url"].startswith("http://") and adapter["prometheus"]["port"]


def test_the_model_claim_can_be_filled_and_is_read_only_to_the_replicas():
    claim = resources("cpu")[("PersistentVolumeClaim", "collider-models")]
    assert claim["spec"]["accessModes"] == ["ReadWriteMany"]
    (loader,) = documents(K8S / "models-loader.yaml")
    kubernetes_validate.validate(loader, MIN_VERSION, strict=True)
    (volume,) = loader["spec"]["volumes"]
    assert volume["persistentVolumeClaim"] == {"claimName": "collider-models"}  # read-write
    (mount,) = loader["spec"]["containers"][0]["volumeMounts"]
    assert mount["mountPath"] == "/models" and not mount.get("readOnly")
    assert loader["spec"]["securityContext"]["runAsUser"] == \
        resources("cpu")[("Deployment", "collider")]["spec"]["template"]["spec"][
            "securityContext"]["runAsUser"]
