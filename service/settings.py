"""Service settings, read from the environment once per process. The embedded default needs none of
them: SQLite and the artifact root live under LECO_DATA_DIR (./leco-data), and a local Ray is
started."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

# where `leco serve` writes a generated API token, in the data folder (mode 600)
TOKEN_FILE = "api-token"


class Settings(BaseModel):
    model_config = ConfigDict(frozen=True)

    data_dir: Path = Path("leco-data")
    database_url: str | None = None  # default: SQLite at data_dir/leco.db
    artifact_root: Path | None = None  # default: data_dir/artifacts (a shared volume in deployment)
    # a Ray Jobs API address (http://head:8265) submits jobs to a cluster
    ray_address: str | None = None
    # bearer tokens; none configured: /v1 is open (embedded default only)
    api_tokens: tuple[str, ...] = ()
    max_upload_bytes: int = Field(2 * 2**30, gt=0)
    # Scene registration decodes every image (in the scene pool's own processes, not the API's): the
    # pixels one scene may decode (3 bytes each while it is checked), how many registrations run at
    # once (processes) and how many may wait (more: 429).
    max_scene_pixels: int = Field(400_000_000, gt=0)
    scene_workers: int = Field(2, ge=1)
    scene_queue: int = Field(4, ge=0)
    # Upload bodies are received before a registration takes a place above: at most this many at
    # once (more: 429), each cut off (408) when it sends nothing for upload_idle_s or, past its
    # first upload_idle_s, averages under upload_min_bytes_per_s. Every other request body (JSON)
    # is cut off by the same two deadlines (service/api/gate.py).
    upload_receivers: int = Field(8, ge=1)
    # ... of which one client address may hold this many
    upload_receivers_per_client: int = Field(2, ge=1)
    upload_idle_s: float = Field(30.0, gt=0)
    upload_min_bytes_per_s: float = Field(16 * 1024, ge=0)
    # `leco serve` without a proxy (service/api/connections.py): a connection whose request headers
    # are not in this many seconds after it opened (or after its last response) is closed, and
    # connections beyond max_connections are closed as they arrive.
    header_timeout_s: float = Field(10.0, gt=0, le=3600)
    max_connections: int = Field(2048, ge=16, le=1_000_000)
    # /v1 requests one bearer token may have unfinished at once (more: 429), so one client cannot
    # take every connection and worker thread (service/api/gate.py)
    max_requests_per_token: int = Field(256, ge=1, le=1_000_000)
    # The dashboard viewer's renders (POST /v1/jobs/{id}/view): processes rendering at once, and
    # requests that may wait for one (more: 429). One process keeps the last few jobs' networks
    # loaded.
    view_workers: int = Field(1, ge=1)
    view_queue: int = Field(1, ge=0)
    # a running job's lease; the dispatcher renews it every lease_s / 4
    lease_s: float = Field(180.0, gt=0)
    # How long training and the dispatcher wait out a database outage before giving up (None: two
    # thirds of the lease). Must end before the lease can lapse (see `check_lease_and_retry`).
    db_retry_s: float | None = Field(None, gt=0)
    max_attempts: int = Field(3, ge=1)  # claims of one job before an expired lease fails it
    # the embedded Ray's CPUs: the most workers a job gets
    local_cpus: int = Field(max(2, os.cpu_count() or 2), ge=1)
    # the GPUs of this machine's backend (the embedded Ray's, the local backend's): the most GPU
    # workers a local job gets (None: those the NVIDIA driver lists, as CUDA_VISIBLE_DEVICES narrows
    # them; service/api/feasibility.py)
    local_gpus: int | None = Field(None, ge=0)
    # checkpoint artifacts kept per job (older ones are deleted)
    keep_checkpoints: int = Field(2, ge=1)
    # how old a polled job view or metrics answer may be (0: no cache)
    poll_cache_s: float = Field(0.5, ge=0)
    # local: one in-process worker without Ray (debugging, quick tests)
    backend: Literal["ray", "local"] = "ray"
    # local backend: each attempt in a child process, so a run out of memory fails its job and not
    # the API (off: in the dispatcher's thread, for a debugger or a method registered in-process)
    local_in_child: bool = True
    # Where a job runs, for the API's memory check: the RAM one job may use (local: all its ranks
    # together; cluster: one rank's worker), default this machine's RAM; in cluster mode the most
    # workers and GPUs a job may ask for (unset GPUs: not checked).
    slot_memory_mb: int = Field(default_factory=lambda: machine_memory_mb(), ge=1)
    cluster_max_workers: int = Field(8, ge=1)
    cluster_gpus: int | None = Field(None, ge=0)

    @model_validator(mode="after")
    def check_lease_and_retry(self) -> "Settings":
        """A run whose writes wait out an outage longer than its lease could outlive it: another
        attempt claims the job while the first still trains (fencing). The last renewal may be a
        heartbeat period (lease / 4) before the outage begins, so the wait must end within the other
        three quarters."""
        if self.retry_s >= 0.75 * self.lease_s:
            raise ValueError(
                f"LECO_DB_RETRY_S ({self.retry_s:g} s) must be shorter than three quarters of "
                f"LECO_LEASE_S ({self.lease_s:g} s, renewed every {self.lease_s / 4:g} s): a run "
                "waiting out a database outage could outlive its lease while a second attempt "
                "trains the same job. Lower LECO_DB_RETRY_S or raise LECO_LEASE_S."
            )
        return self

    @property
    def retry_s(self) -> float:
        return self.db_retry_s if self.db_retry_s is not None else self.lease_s * 2 / 3

    @property
    def db_url(self) -> str:
        return self.database_url or f"sqlite:///{(self.data_dir / 'leco.db').resolve()}"

    @property
    def artifacts(self) -> Path:
        return (self.artifact_root or self.data_dir / "artifacts").resolve()

    @property
    def scenes_dir(self) -> Path:
        return (self.data_dir / "scenes").resolve()

    @property
    def runs_dir(self) -> Path:
        return (self.data_dir / "runs").resolve()

    @property
    def embedded(self) -> bool:
        return self.database_url is None or self.database_url.startswith("sqlite")

    @classmethod
    def from_env(cls, **overrides: Any) -> "Settings":
        env = os.environ
        values: dict = {}
        if env.get("LECO_DATA_DIR"):
            values["data_dir"] = Path(env["LECO_DATA_DIR"])
        if env.get("DATABASE_URL"):
            values["database_url"] = env["DATABASE_URL"]
        if env.get("LECO_ARTIFACT_ROOT"):
            values["artifact_root"] = Path(env["LECO_ARTIFACT_ROOT"])
        if env.get("LECO_RAY_JOBS_ADDRESS"):
            values["ray_address"] = env["LECO_RAY_JOBS_ADDRESS"]
        if "LECO_API_TOKENS" in env:
            values["api_tokens"] = tuple(
                t.strip() for t in env["LECO_API_TOKENS"].split(",") if t.strip()
            )
            if not values["api_tokens"]:  # set but blank must not mean "no auth"
                raise ValueError(
                    "LECO_API_TOKENS is set but holds no token (only spaces or commas): set "
                    "tokens, or unset it and let `leco serve` make one"
                )
        for key, name in (
            ("max_upload_bytes", "LECO_MAX_UPLOAD_BYTES"),
            ("lease_s", "LECO_LEASE_S"),
            ("db_retry_s", "LECO_DB_RETRY_S"),
            ("max_attempts", "LECO_MAX_ATTEMPTS"),
            ("local_cpus", "LECO_LOCAL_CPUS"),
            ("local_gpus", "LECO_LOCAL_GPUS"),
            ("backend", "LECO_BACKEND"),
            ("local_in_child", "LECO_LOCAL_IN_CHILD"),
            ("poll_cache_s", "LECO_POLL_CACHE_S"),
            ("slot_memory_mb", "LECO_SLOT_MEMORY_MB"),
            ("cluster_max_workers", "LECO_CLUSTER_MAX_WORKERS"),
            ("cluster_gpus", "LECO_CLUSTER_GPUS"),
            ("max_scene_pixels", "LECO_MAX_SCENE_PIXELS"),
            ("scene_workers", "LECO_SCENE_WORKERS"),
            ("scene_queue", "LECO_SCENE_QUEUE"),
            ("view_workers", "LECO_VIEW_WORKERS"),
            ("view_queue", "LECO_VIEW_QUEUE"),
            ("upload_receivers", "LECO_UPLOAD_RECEIVERS"),
            ("upload_idle_s", "LECO_UPLOAD_IDLE_S"),
            ("upload_receivers_per_client", "LECO_UPLOAD_RECEIVERS_PER_CLIENT"),
            ("upload_min_bytes_per_s", "LECO_UPLOAD_MIN_BYTES_PER_S"),
            ("header_timeout_s", "LECO_HEADER_TIMEOUT_S"),
            ("max_requests_per_token", "LECO_MAX_REQUESTS_PER_TOKEN"),
            ("max_connections", "LECO_MAX_CONNECTIONS"),
        ):
            if env.get(name):
                values[key] = env[name]
        try:
            return cls(**{**values, **overrides})
        # a plain message naming each setting (not "invalid job config")
        except ValidationError as error:
            problems = "; ".join(
                f"{'.'.join(map(str, e['loc'])) or 'settings'}: {e['msg']}" for e in error.errors()
            )
            raise ValueError(f"invalid service settings: {problems}") from None


def machine_memory_mb() -> int:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2**20
    except (ValueError, OSError, AttributeError):  # not POSIX: no check beyond the schema's bounds
        return 2**31 - 1
