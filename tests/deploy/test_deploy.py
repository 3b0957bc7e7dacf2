"""The deployment files, checked without a Docker engine: docker-compose.yml's topology (services,
dependencies, health checks, the shared volume, the read-only LPIPS weights, shm, Ray auth, secrets
from .env) and that every command it runs exists in the project; the Dockerfiles' pins and sources;
the KubeRay manifests' GPU workers, shared storage and LPIPS weights."""

import ipaddress
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.helpers import ROOT

LECO_SERVICES = {"migrate", "ray-head", "ray-worker", "api", "dispatcher"}


def env_example() -> dict[str, str]:
    lines = (ROOT / ".env.example").read_text().splitlines()
    return dict(line.split("=", 1) for line in lines if line.strip() and not line.startswith("#"))


def interpolate(text: str, env: dict[str, str]) -> str:
    """Compose's ${VAR}, ${VAR:-default} and ${VAR:?error}; $$ is a literal $."""

    def value(match):
        name, op, arg = match.group(1), match.group(2), match.group(3)
        if name in env:
            return env[name]
        if op == ":-":
            return arg
        raise AssertionError(f"compose needs ${{{name}}}, which .env.example does not set")

    text = text.replace("$$", "\0")
    text = re.sub(r"\$\{([A-Z0-9_]+)(?:(:-|:\?)([^}]*))?\}", value, text)
    return text.replace("\0", "$")


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(interpolate((ROOT / "docker-compose.yml").read_text(), env_example()))


def test_compose_has_the_whole_topology(compose):
    services = compose["services"]
    assert set(services) == {"postgres", "proxy"} | LECO_SERVICES
    depends = {name: s.get("depends_on", {}) for name, s in services.items()}
    assert depends["migrate"] == {"postgres": {"condition": "service_healthy"}}
    for name in ("api", "dispatcher"):
        assert depends[name]["migrate"] == {"condition": "service_completed_successfully"}
    assert depends["dispatcher"]["ray-head"] == {"condition": "service_healthy"}
    assert depends["ray-worker"] == {"ray-head": {"condition": "service_healthy"}}
    assert services["ray-worker"]["deploy"]["replicas"] >= 2  # scalable CPU workers
    assert services["migrate"]["restart"] == "no"  # one-shot
    # Stopped, the dispatcher hands its jobs back and waits up to 20 s for their runs to checkpoint.
    assert int(services["dispatcher"]["stop_grace_period"].rstrip("s")) > 20
    for name, service in services.items():
        if name != "migrate":
            assert service["healthcheck"]["test"][0] == "CMD", name


def test_compose_shares_one_volume_auth_and_secrets(compose):
    services = compose["services"]
    assert set(compose["volumes"]) == {"leco-data", "postgres-data"}
    for name in LECO_SERVICES:
        service = services[name]
        assert service["volumes"][0] == "leco-data:/data", name  # the same path everywhere
        env = service["environment"]
        assert env["LECO_DATA_DIR"] == "/data" and env["LECO_ARTIFACT_ROOT"].startswith("/data/")
        assert (
            env["RAY_AUTH_MODE"] == "token"
            and env["RAY_AUTH_TOKEN"] == env_example()["RAY_AUTH_TOKEN"]
        )
        assert (
            env["DATABASE_URL"].startswith("postgresql+psycopg://leco:")
            and "@postgres:5432/" in env["DATABASE_URL"]
        )
        assert service["env_file"] == ".env"
        gigabytes = int(service["shm_size"].removesuffix("gb"))
        assert gigabytes >= 1
    # No secret is written into the compose file itself: each comes from .env.
    raw = (ROOT / "docker-compose.yml").read_text()
    for secret in ("POSTGRES_PASSWORD", "RAY_AUTH_TOKEN"):
        assert f"${{{secret}:?" in raw
    assert ".env" in (ROOT / ".gitignore").read_text().splitlines()


def test_compose_mounts_the_lpips_weights_read_only(compose):
    """Every LeCO container sees the staged LPIPS weights at LECO_LPIPS_DIR, read-only (evaluation
    runs on the Ray nodes and wherever `leco eval` is called); the host folder is ignored by git."""
    for name in LECO_SERVICES:
        service = compose["services"][name]
        assert service["environment"]["LECO_LPIPS_DIR"] == "/lpips", name
        assert f"{env_example()['LECO_LPIPS_HOST_DIR']}:/lpips:ro" in service["volumes"], name
    assert (
        "${LECO_LPIPS_HOST_DIR:-./lpips-weights}:/lpips:ro"
        in (ROOT / "docker-compose.yml").read_text()
    )
    assert "/lpips-weights/" in (ROOT / ".gitignore").read_text().splitlines()


def commands(compose):
    for name, service in compose["services"].items():
        if name in ("postgres", "proxy"):
            continue
        words = service["command"]
        if words[:2] == ["sh", "-c"]:
            words = shlex.split(words[2].replace("${RAY_WORKER_CPUS:-2}", "2"))
        yield name, words
        check = service.get("healthcheck", {}).get("test", [])[1:]
        if check and check[0] in ("python", "ray", "leco"):
            yield f"{name} healthcheck", check


def test_every_command_the_compose_file_runs_exists(compose):
    from ray.scripts.scripts import cli as ray_cli

    from cli.main import build_parser

    seen = set()
    for name, words in commands(compose):
        program = words[0]
        seen.add(program)
        if program == "leco":
            # exits (fails the test) on an unknown command or flag
            build_parser().parse_args(words[1:])
        elif program == "ray":
            command = ray_cli.commands[words[1]]
            options = {o for p in command.params for o in p.opts}
            for word in words[2:]:
                assert word.split("=")[0] in options, f"{name}: ray {words[1]} has no option {word}"
        elif program == "python":
            assert words[1] == "-c"
            # the imports resolve
            exec(compile(words[2].split("; check_schema")[0], name, "exec"), {})
        else:
            raise AssertionError(f"{name} runs {program}, which this test does not know")
    assert seen == {"leco", "ray", "python"}


NGINX_DEADLINES = (
    "client_header_timeout 10s;",
    "client_body_timeout 30s;",
    "limit_conn leco_per_client 64;",
    "limit_conn_status 429;",
    "limit_req zone=leco_writes burst=60 nodelay;",
    "proxy_request_buffering off;",
    "proxy_pass http://${LECO_API_UPSTREAM};",
)


def test_clients_reach_the_api_through_nginx_only(compose):
    """docker-compose publishes the proxy's port, never the API's; the proxy renders
    deploy/nginx.conf.template, which holds the deadlines and limits docs/SERVICE.md and
    deploy/README.md promise."""
    services = compose["services"]
    assert "ports" not in services["api"] and services["api"]["expose"] == ["8765"]
    # ... and takes X-Forwarded-For only from the proxy's fixed address on a network the two share
    # with nobody else: no other container can name the client its per-client limits count
    proxy = services["proxy"]
    address = proxy["networks"]["edge"]["ipv4_address"]
    assert services["api"]["command"][-2:] == ["--trusted-proxies", address]
    assert ipaddress.ip_address(address) in ipaddress.ip_network(
        compose["networks"]["edge"]["ipam"]["config"][0]["subnet"]
    )
    on_edge = [n for n, s in services.items() if "edge" in (s.get("networks") or [])]
    assert sorted(on_edge) == ["api", "proxy"] and "edge" in services["api"]["networks"]
    assert re.fullmatch(r"nginx:\d+\.\d+\.\d+-bookworm", proxy["image"])  # pinned
    assert proxy["ports"] == [f"{env_example().get('LECO_PORT', '8765')}:8080"]
    assert proxy["environment"]["LECO_API_UPSTREAM"] == "api:8765"
    assert proxy["volumes"] == [
        "./deploy/nginx.conf.template:/etc/nginx/templates/default.conf.template:ro"
    ]
    assert proxy["depends_on"] == {"api": {"condition": "service_healthy"}}
    template = (ROOT / "deploy" / "nginx.conf.template").read_text()
    for directive in NGINX_DEADLINES:
        assert directive in template, directive
    assert "listen 8080;" in template and template.count("{") == template.count("}")
    documents = list(yaml.safe_load_all((ROOT / "deploy" / "kuberay" / "service.yaml").read_text()))
    (api,) = [
        d for d in documents if d["metadata"]["name"] == "leco-api" and d["kind"] == "Deployment"
    ]
    sidecar = api["spec"]["template"]["spec"]["containers"][1]
    assert sidecar["image"] == proxy["image"] and sidecar["env"] == [
        {"name": "LECO_API_UPSTREAM", "value": "127.0.0.1:8765"}
    ]
    (service,) = [d for d in documents if d["kind"] == "Service"]
    assert service["spec"]["ports"][0]["targetPort"] == 8080
    assert (
        "kubectl create configmap leco-nginx --from-file=deploy/nginx.conf.template"
        in (ROOT / "deploy" / "README.md").read_text()
    )


def test_the_nginx_template_is_a_config_nginx_accepts(tmp_path):
    """The template rendered as the nginx image renders it (envsubst of ${LECO_API_UPSTREAM}),
    checked by a real nginx (`nginx -t`), where one is installed (Debian: apt-get install nginx)."""
    nginx = shutil.which("nginx") or next(
        (p for p in ("/usr/sbin/nginx",) if Path(p).exists()), None
    )
    if nginx is None:
        pytest.skip(
            "nginx is not installed here (apt-get install nginx): the template's syntax is not "
            "checked"
        )
    template = (ROOT / "deploy" / "nginx.conf.template").read_text()
    (tmp_path / "default.conf").write_text(
        template.replace("${LECO_API_UPSTREAM}", "127.0.0.1:8765")
    )
    (tmp_path / "nginx.conf").write_text(
        f"pid {tmp_path}/nginx.pid;\nerror_log {tmp_path}/error.log;\nevents {{}}\nhttp {{ "
        f"access_log off; client_body_temp_path {tmp_path}; proxy_temp_path {tmp_path}; include "
        f"{tmp_path}/default.conf; }}\n"
    )
    checked = subprocess.run(
        [nginx, "-t", "-p", str(tmp_path), "-c", str(tmp_path / "nginx.conf")],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert checked.returncode == 0, checked.stderr


def test_dockerfiles_are_pinned_and_copy_what_exists():
    for variant in ("cpu", "cuda"):
        text = (ROOT / "deploy" / f"Dockerfile.{variant}").read_text()
        base = re.search(r"^FROM (\S+)", text, re.M).group(1)
        assert re.fullmatch(r"python:3\.11\.\d+-slim-bookworm", base), base
        assert "torch==2.13.0" in text
        for source in re.findall(r"^COPY (\S+)", text, re.M):
            assert (ROOT / source).exists(), (
                f"Dockerfile.{variant} copies {source}, which is missing"
            )
        assert "pip install -e ." in text  # migrations/ must stay beside service/
        assert re.search(r"^USER (?!root)", text, re.M)


def test_kuberay_manifests_give_8_gpu_workers_shared_storage_and_auth():
    cluster = yaml.safe_load((ROOT / "deploy" / "kuberay" / "raycluster.yaml").read_text())
    assert cluster["kind"] == "RayCluster" and cluster["spec"]["rayVersion"] == "2.60.0"
    head = cluster["spec"]["headGroupSpec"]["template"]["spec"]
    (group,) = cluster["spec"]["workerGroupSpecs"]
    worker = group["template"]["spec"]
    assert group["rayStartParams"]["num-gpus"] == "8"
    assert worker["containers"][0]["resources"]["limits"]["nvidia.com/gpu"] == "8"
    assert worker["containers"][0]["image"].endswith("-cuda")
    documents = list(yaml.safe_load_all((ROOT / "deploy" / "kuberay" / "service.yaml").read_text()))
    (config,) = [d for d in documents if d["kind"] == "ConfigMap"]
    assert config["data"]["RAY_AUTH_MODE"] == "token" and config["data"]["LECO_DATA_DIR"] == "/data"
    pods = [head, worker] + [
        d["spec"]["template"]["spec"] for d in documents if d["kind"] in ("Job", "Deployment")
    ]
    # every pod: the same settings and secrets, so Ray auth and paths agree everywhere
    for spec in pods:
        assert spec["containers"][0]["envFrom"] == [
            {"configMapRef": {"name": "leco-env"}},
            {"secretRef": {"name": "leco-secrets"}},
        ]
    for spec in (head, worker):
        container = spec["containers"][0]
        assert {"name": "leco-data", "mountPath": "/data"} in container["volumeMounts"]
        assert {"name": "dshm", "mountPath": "/dev/shm"} in container["volumeMounts"]
    # The LPIPS weights: staged once in lpips-weights/ on the shared volume, read-only at
    # LECO_LPIPS_DIR on every pod that evaluates (the Ray nodes) or may (the API and the
    # dispatcher).
    assert config["data"]["LECO_LPIPS_DIR"] == "/lpips"
    lpips_mount = {
        "name": "leco-data",
        "mountPath": "/lpips",
        "subPath": "lpips-weights",
        "readOnly": True,
    }
    deployments = [d["spec"]["template"]["spec"] for d in documents if d["kind"] == "Deployment"]
    for spec in [head, worker] + deployments:
        assert lpips_mount in spec["containers"][0]["volumeMounts"]
        assert "leco-data" in {v["name"] for v in spec["volumes"]}
    (dispatcher,) = [d for d in documents if d["metadata"]["name"] == "leco-dispatcher"]
    assert dispatcher["spec"]["template"]["spec"]["terminationGracePeriodSeconds"] > 20
    claim = yaml.safe_load((ROOT / "deploy" / "kuberay" / "pvc.yaml").read_text())
    assert claim["spec"]["accessModes"] == ["ReadWriteMany"]
    assert [d["kind"] for d in documents] == [
        "ConfigMap",
        "Job",
        "Deployment",
        "Deployment",
        "Service",
    ]
