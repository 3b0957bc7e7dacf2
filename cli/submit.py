"""`leco submit`: a client of the HTTP API. It finds or registers the scene, submits the job with an
Idempotency-Key (a retried submit never makes a second job), follows it with a progress line, and
prints the summary and where the artifacts are."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from model.errors import Failed
from service.settings import TOKEN_FILE

if TYPE_CHECKING:
    import httpx  # imported where used at run time, so the CLI starts without it


class ClientError(Failed):
    pass


class Api:
    def __init__(self, url: str, token: str | None, timeout: float = 30.0, retry_s: float = 120.0):
        import httpx

        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.url, self.retry_s = url.rstrip("/"), retry_s
        self.http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout)

    def call(
        self, method: str, path: str, ok: tuple[int, ...] = (200, 201, 202, 204), **kwargs: Any
    ) -> httpx.Response:
        """One request; while the service restarts (no connection) or says it is briefly unavailable
        (502, 503,
        504) it is retried for up to `retry_s` seconds. Submits carry an Idempotency-Key, so a retry
             never
        makes a second job."""
        response = self._send(method, path, **kwargs)
        if response.status_code not in ok:
            try:
                detail = response.json().get("detail")
            except ValueError:
                detail = response.text
            raise ClientError(f"{method} {path}: HTTP {response.status_code}: {detail}")
        return response

    def _send(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """The first answer other than 502-504, or the last answer when `retry_s` runs out."""
        import httpx

        deadline, pause = time.monotonic() + self.retry_s, 0.5
        response: httpx.Response | None
        while True:
            try:
                response = self.http.request(method, path, **kwargs)
                if response.status_code not in (502, 503, 504):
                    return response
                problem = f"HTTP {response.status_code}"
            except httpx.TransportError as error:
                response, problem = None, f"{type(error).__name__}: {error}"
            if time.monotonic() + pause > deadline:
                if response is not None:
                    return response
                raise ClientError(
                    f"cannot reach the service at {self.url} for {self.retry_s:.0f} s: {problem}"
                )
            time.sleep(pause)
            pause = min(pause * 2, 5.0)


def default_token(data_dir: str | None) -> str | None:
    if os.environ.get("LECO_TOKEN"):
        return os.environ["LECO_TOKEN"]
    path = Path(data_dir or os.environ.get("LECO_DATA_DIR", "leco-data")) / TOKEN_FILE
    return path.read_text().strip() if path.is_file() else None


def photos_archive(path: Path) -> bytes:
    """A tar of a folder of photos (an archive given as it is)."""
    if not path.is_dir():
        return path.read_bytes()
    import io
    import tarfile

    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(path, arcname=path.name)
    return buffer.getvalue()


def ensure_scene(api: Api, args: argparse.Namespace) -> dict:
    if args.photos:
        name = args.name or Path(args.photos).name.split(".")[0]
        settings = dict(item.partition("=")[::2] for item in args.poses_set or [])
        return api.call(
            "POST",
            "/v1/scenes/photos",
            params={"name": name, **settings},
            content=photos_archive(Path(args.photos)),
            headers={"Content-Type": "application/octet-stream"},
        ).json()
    if args.upload:
        name = args.name or Path(args.upload).name.split(".")[0]
        with open(args.upload, "rb") as f:
            return api.call(
                "POST",
                "/v1/scenes/upload",
                params={"name": name},
                content=f.read(),
                headers={"Content-Type": "application/octet-stream"},
            ).json()
    if args.synthetic:
        preset, _, seed = args.synthetic.partition(":")
        name = args.name or f"{preset}-{seed or 0}"
        found = api.call("GET", f"/v1/scenes/{name}", ok=(200, 404))
        if found.status_code == 200:
            return found.json()
        return api.call(
            "POST",
            "/v1/scenes/synthetic",
            json={"name": name, "preset": preset, "seed": int(seed or 0)},
        ).json()
    return api.call("GET", f"/v1/scenes/{args.scene}").json()


def wait_ready(api: Api, scene: dict, stream: TextIO) -> dict:
    if scene["state"] == "posing":  # its poses job, followed as any job
        stream.write(f"finding the poses of scene {scene['name']}'s photos ...\n")
        follow(api, scene["poses_job"], stream)
        scene = api.call("GET", f"/v1/scenes/{scene['id']}").json()
    if scene["state"] == "generating":
        stream.write(
            f"generating scene {scene['name']} (preset {scene['generator']['preset']}) ...\n"
        )
        stream.flush()
    while scene["state"] == "generating":
        time.sleep(2)
        scene = api.call("GET", f"/v1/scenes/{scene['id']}").json()
    if scene["state"] != "ready":
        raise ClientError(f"scene {scene['name']} is {scene['state']}: {scene.get('error')}")
    return scene


def progress_line(job: dict) -> str:
    metrics = (job.get("latest_metrics") or {}).get(job.get("phase") or "", {})
    parts = [
        f"job {job['id']} {job['state']}",
        f"[{job.get('phase') or '-'}] step {job['step']}/{job['total_steps']}",
        f"{job['percent']:.0f}%",
    ]
    if job.get("rays_per_s"):
        parts.append(f"{job['rays_per_s']:,.0f} rays/s")
    if metrics.get("psnr") is not None:
        parts.append(f"PSNR {metrics['psnr']:.2f}")
    if job.get("eta_s") is not None:
        parts.append(f"ETA {int(job['eta_s'] // 60)}m{int(job['eta_s'] % 60):02d}s")
    return " | ".join(parts)


def follow(api: Api, job_id: int, stream: TextIO, poll_s: float = 2.0) -> dict:
    last = ""
    while True:
        job = api.call("GET", f"/v1/jobs/{job_id}").json()
        line = progress_line(job)
        if line != last:
            stream.write(("\r" + line.ljust(len(last))) if stream.isatty() else line + "\n")
            stream.flush()
            last = line
        if job["state"] in ("succeeded", "failed", "cancelled"):
            if stream.isatty():
                stream.write("\n")
            return job
        time.sleep(poll_s)


def submit_command(args: argparse.Namespace) -> int:
    from workers.config import parse_overrides

    api = Api(args.url, args.token or default_token(args.data_dir))
    stream = sys.stderr
    scene = wait_ready(api, ensure_scene(api, args), stream)
    body = {
        "scene": scene["id"],
        "method": args.method,
        "profile": args.profile,
        "overrides": parse_overrides(args.set or []),
        "workers": args.workers,
        "use_gpu": args.gpu,
        "budget_min": args.budget_min,
        "seed": args.seed,
        "eval_every_s": args.eval_every_s,
        "downscale": args.downscale,
        "compile": args.compile,
    }
    job = api.call(
        "POST", "/v1/jobs", json=body, headers={"Idempotency-Key": str(uuid.uuid4())}
    ).json()
    print(
        f"submitted job {job['id']} ({args.method}, profile {args.profile}) on scene "
        f"{scene['name']}: {api.url}/v1/jobs/{job['id']}",
        file=stream,
        flush=True,
    )
    if args.no_follow:
        print(json.dumps({"job": job["id"], "state": job["state"]}))
        return 0
    try:
        job = follow(api, job["id"], stream)
    except KeyboardInterrupt:
        print(
            f"\nstopped following; job {job['id']} goes on (cancel: POST "
            f"{api.url}/v1/jobs/{job['id']}/cancel)",
            file=stream,
        )
        return 130
    artifacts = api.call("GET", f"/v1/jobs/{job['id']}/artifacts").json()
    result = {
        "job": job["id"],
        "state": job["state"],
        "error": job["error"],
        "artifacts": [
            f"{api.url}{a['url']}  {a['kind']:15s} {a['name']} ({a['size']:,} bytes)"
            for a in artifacts
        ],
    }
    summary = next((a for a in artifacts if a["name"] == "summary.json"), None)
    if summary is not None:
        data = api.call("GET", summary["url"]).json()
        result["summary"] = {
            k: data.get(k)
            for k in (
                "method",
                "profile",
                "wall_time_s",
                "steps",
                "rays_per_s",
                "samples_per_ray",
                "occupancy",
                "val",
                "peak_memory_mb",
            )
        }
    print(json.dumps(result, indent=2))
    return 0 if job["state"] == "succeeded" else 1


def add_submit(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sub = commands.add_parser(
        "submit", help="submit a job to a running service and follow it to the end"
    )
    sub.add_argument("--url", default=os.environ.get("LECO_URL", "http://127.0.0.1:8765"))
    sub.add_argument(
        "--token", help="bearer token (default: $LECO_TOKEN, or the api-token file of --data-dir)"
    )
    sub.add_argument(
        "--data-dir",
        help="where `leco serve` keeps its token (default: $LECO_DATA_DIR or ./leco-data)",
    )
    where = sub.add_mutually_exclusive_group(required=True)
    where.add_argument("--scene", help="a registered scene's id or name")
    where.add_argument(
        "--synthetic",
        metavar="PRESET[:SEED]",
        help="a synthetic city, registered if new (e.g. city:0)",
    )
    where.add_argument(
        "--upload", metavar="ARCHIVE", help="a tar or zip of a scene folder to register"
    )
    where.add_argument(
        "--photos",
        metavar="FOLDER|ARCHIVE",
        help="photos without poses (a folder, or a tar or zip): the service finds their poses, "
        "then trains",
    )
    sub.add_argument(
        "--poses-set",
        action="append",
        metavar="KEY=VALUE",
        help="with --photos: a poses setting (repeatable; `leco scene poses --help` lists them)",
    )
    sub.add_argument("--name", help="name for a new scene")
    # Not checked here: the service knows its methods (GET /v1/methods) and answers 422 naming them.
    sub.add_argument("--method", default="leco", help="a method the service knows (default: leco)")
    sub.add_argument("--profile", default="cpu", help="smoke | cpu | paper (default: cpu)")
    sub.add_argument("--workers", type=int, default=1)
    sub.add_argument("--gpu", action="store_true")
    sub.add_argument("--budget-min", type=float, default=None)
    sub.add_argument("--seed", type=int, default=0)
    sub.add_argument(
        "--downscale",
        type=int,
        default=None,
        help="integer factor for images and intrinsics, in training and evaluation alike (default: "
        "the scene's own scale; the paper uses 4 on Mega-NeRF scenes)",
    )
    sub.add_argument(
        "--eval-every-s",
        type=float,
        default=None,
        help="validation PSNR every this many training seconds (the dashboard's comparison uses "
        "it)",
    )
    sub.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="profile override (repeatable; `leco settings` lists them)",
    )
    sub.add_argument(
        "--compile",
        action="store_true",
        help="compile the networks with torch.compile (inductor), the compiling counted as "
        "training time",
    )
    sub.add_argument("--no-follow", action="store_true", help="submit and return")
    sub.set_defaults(func=submit_command)
