"""`leco serve` (API + dispatcher + local Ray), `leco dispatch` (dispatcher only), `leco db
upgrade`."""

from __future__ import annotations

import argparse
import gc
import logging
import os
import secrets
import signal
import threading
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, Callable

from service.settings import TOKEN_FILE

if TYPE_CHECKING:
    import uvicorn

    from service.settings import Settings


def settings_from(args: argparse.Namespace, **overrides: Any) -> Settings:
    from service.settings import Settings

    if getattr(args, "data_dir", None):
        overrides["data_dir"] = Path(args.data_dir)
    return Settings.from_env(**overrides)


def db_upgrade(args: argparse.Namespace) -> int:
    from service.db import redact, upgrade

    settings = settings_from(args)
    before, after = upgrade(settings.db_url)
    print(f"database {redact(settings.db_url)}: {before or 'empty'} -> {after}")
    return 0


def prepare(settings: Settings, upgrade_embedded: bool) -> None:
    """The embedded default migrates for the user; any other database must already be at the schema.
    Then whatever a crash left in the artifact store goes (staged files an hour old, blobs no row
    references)."""
    from service.db import check_schema, upgrade

    if upgrade_embedded and settings.embedded and settings.database_url is None:
        upgrade(settings.db_url)
    check_schema(settings.db_url)
    collect_orphans(settings)
    # Training pixel caches (model/scenes/pixel_cache.py) live on the data volume, shared by every
    # job and, through the environment Ray's workers inherit, by every rank on this node.
    os.environ.setdefault("LECO_PIXEL_CACHE", str(settings.data_dir.resolve() / "pixel-cache"))


def collect_orphans(settings: Settings) -> dict:
    from service.store import ArtifactStore

    if not settings.artifacts.is_dir():
        return {"staged": 0, "blobs": 0, "bytes": 0}
    removed = ArtifactStore(settings.db_url, settings.artifacts).collect_orphans()
    if removed["staged"] or removed["blobs"]:
        logging.getLogger("leco.store").warning(
            "removed %d staged file(s) and %d unreferenced blob(s) (%d bytes) left by a crash",
            removed["staged"],
            removed["blobs"],
            removed["bytes"],
        )
    return removed


def db_gc(args: argparse.Namespace) -> int:
    removed = collect_orphans(settings_from(args))
    print(
        f"artifact store: removed {removed['staged']} staged file(s) and {removed['blobs']} "
        f"unreferenced blob(s), {removed['bytes']:,} bytes"
    )
    return 0


def start_ray(settings: Settings) -> None:
    if settings.ray_address or settings.backend != "ray":
        return
    from workers.train.run import ensure_ray

    # here, in the main thread: Ray installs signal handlers
    ensure_ray(settings.local_cpus, settings.local_gpus)


def releasing_server(config: uvicorn.Config, on_exit: Callable[[], None] | None) -> uvicorn.Server:
    """uvicorn's server, which on SIGTERM or Ctrl-C first calls `on_exit` (returning the running
    jobs to the queue) and then shuts down gracefully. A subclass made here so that uvicorn is
    imported only to serve."""
    import uvicorn

    class ReleasingServer(uvicorn.Server):
        def handle_exit(self, sig: int, frame: FrameType | None) -> None:
            if on_exit is not None and not self.should_exit:
                on_exit()
            super().handle_exit(sig, frame)

    return ReleasingServer(config)


def serve(args: argparse.Namespace) -> int:
    import uvicorn

    from service.api.app import create_app
    from service.dispatcher import Dispatcher
    from service.scenes import resume_generation

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger("alembic").setLevel(logging.WARNING)
    overrides = {}
    token = None
    if args.no_auth and not loopback(args.host):
        raise SystemExit(
            f"leco serve: --no-auth with --host {args.host} would open the API to the network; use "
            "it only with a loopback host (127.0.0.1, ::1, localhost)"
        )
    if not args.no_auth and "LECO_API_TOKENS" not in os.environ:
        token = secrets.token_urlsafe(24)
        while token.startswith("-"):  # `leco submit --token -x...` would read it as an option
            token = secrets.token_urlsafe(24)
        overrides["api_tokens"] = (token,)
    settings = settings_from(args, **overrides)
    prepare(settings, upgrade_embedded=True)
    if token:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        write_private(settings.data_dir / TOKEN_FILE, token)
    start_ray(settings)
    app = create_app(settings)
    resume_generation(settings, app.state.scene_pool)
    dispatcher = None
    if not args.no_dispatcher:
        dispatcher = Dispatcher(settings, slots=args.slots)
        threading.Thread(target=dispatcher.run_forever, daemon=True, name="leco-dispatcher").start()
    print(
        f"LeCO-NeRF service at http://{args.host}:{args.port} (API docs: /docs; data: "
        f"{settings.data_dir.resolve()})",
        flush=True,
    )
    if token:
        # The file only: stdout ends up in log files (make run's serve.log), and tokens are never
        # logged.
        print(
            f"API token in {(settings.data_dir / TOKEN_FILE).resolve()} (mode 600; leco submit "
            "reads it)",
            flush=True,
        )
    # Everything imported and built so far lives as long as the process: keep it out of the
    # collector's sweeps, or each full collection (hundreds of thousands of objects: torch,
    # SQLAlchemy, pydantic) stalls every request in flight for ~100 ms.
    gc.freeze()
    from service.api.connections import connection_budget, guarded_protocol

    protocol = guarded_protocol(
        settings.header_timeout_s, connection_budget(settings.max_connections)
    )
    # The client address the per-client limits count is the one a trusted proxy forwards
    # (X-Forwarded-For); uvicorn trusts only 127.0.0.1 unless told (a sidecar proxy in the same pod
    # is 127.0.0.1).
    config = uvicorn.Config(
        app,
        host=args.host,
        port=args.port,
        log_level="warning",
        http=protocol,
        proxy_headers=True,
        forwarded_allow_ips=args.trusted_proxies,
    )
    server = releasing_server(config, on_exit=dispatcher.release_all if dispatcher else None)
    try:
        server.run()
    except KeyboardInterrupt:
        # uvicorn raises Ctrl-C again once it has shut down; the jobs are already back in the queue
        pass
    finally:
        if dispatcher is not None:
            dispatcher.shutdown()
    return 0


def dispatch(args: argparse.Namespace) -> int:
    from service.db import redact
    from service.dispatcher import Dispatcher

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger("alembic").setLevel(logging.WARNING)
    settings = settings_from(args)
    prepare(settings, upgrade_embedded=False)
    start_ray(settings)
    dispatcher = Dispatcher(settings, slots=args.slots)
    print(f"dispatcher {dispatcher.owner} polling {redact(settings.db_url)}", flush=True)

    # SIGTERM (docker stop) or Ctrl-C: hand the running jobs back first
    def stop(signum: int, frame: FrameType | None) -> None:
        dispatcher.release_all()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    dispatcher.run_forever()  # returns once release_all() has set `stopping`
    dispatcher.shutdown()
    return 0


def add_commands(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    db = commands.add_parser("db", help="database schema and artifact store upkeep").add_subparsers(
        dest="action", required=True
    )
    up = db.add_parser(
        "upgrade", help="apply the Alembic migrations (DATABASE_URL, or the embedded SQLite)"
    )
    up.add_argument(
        "--data-dir", help="embedded data folder (default: $LECO_DATA_DIR or ./leco-data)"
    )
    up.set_defaults(func=db_upgrade)
    gc = db.add_parser(
        "gc",
        help="remove what a crash left in the artifact store (staged files, unreferenced blobs)",
    )
    gc.add_argument(
        "--data-dir", help="embedded data folder (default: $LECO_DATA_DIR or ./leco-data)"
    )
    gc.set_defaults(func=db_gc)

    srv = commands.add_parser(
        "serve", help="run the API, a dispatcher and a local Ray (SQLite by default)"
    )
    srv.add_argument("--host", default="127.0.0.1")
    srv.add_argument("--port", type=int, default=8765)
    srv.add_argument(
        "--data-dir", help="embedded data folder (default: $LECO_DATA_DIR or ./leco-data)"
    )
    srv.add_argument(
        "--slots", type=int, default=1, help="jobs this dispatcher runs at once (default 1)"
    )
    srv.add_argument(
        "--no-auth", action="store_true", help="no bearer token (only for a loopback-only service)"
    )
    srv.add_argument(
        "--no-dispatcher", action="store_true", help="API only; run `leco dispatch` elsewhere"
    )
    srv.add_argument(
        "--trusted-proxies",
        default="127.0.0.1",
        help="addresses whose X-Forwarded-For names the client (comma-separated, or '*' when only "
        "a proxy can reach the API; default 127.0.0.1)",
    )
    srv.set_defaults(func=serve)

    dsp = commands.add_parser(
        "dispatch", help="run a dispatcher only (claims and runs queued jobs)"
    )
    dsp.add_argument(
        "--data-dir", help="embedded data folder (default: $LECO_DATA_DIR or ./leco-data)"
    )
    dsp.add_argument("--slots", type=int, default=1)
    dsp.set_defaults(func=dispatch)

    from cli.submit import add_submit

    add_submit(commands)


def loopback(host: str) -> bool:
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def write_private(path: Path, text: str) -> None:
    """Created 0600 from the first byte (never readable by others, not even briefly) and swapped in
    atomically."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w") as out:
            out.write(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
