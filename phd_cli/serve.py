"""`phd serve`: run the REST service (uvicorn, one process, a pool of worker threads)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "serve", help="run the PH-Dropout REST service",
        description="Serve the web page (at /ui/) and the REST API (OpenAPI docs at /docs). Caps and the API "
                    "key come from PHD_* environment variables (PHD_API_KEY, PHD_MAX_UPLOAD_BYTES, ...; "
                    "see docs/service.md).")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    parser.add_argument("--data-dir", type=Path, default=None,
                        help="models, metadata and calibrations (default: PHD_DATA_DIR, else the user's data dir)")
    parser.add_argument("--workers", type=int, default=None,
                        help="threads running PH-Dropout work at once (default: PHD_WORKERS, else 1)")
    parser.add_argument("--queue-size", type=int, default=None,
                        help="jobs that may wait for a worker before requests get 429 (default 8)")
    parser.add_argument("--ray", metavar="auto|local|ADDRESS", default=None,
                        help="run the jobs' rendering on this Ray cluster (default: PHD_EXECUTOR, else in the "
                             "service's own worker threads; docs/scale-out.md)")
    parser.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn  # web code stays out of phd_core's import path
    from pydantic import ValidationError

    from phd_core.errors import InputError
    from service.app import create_app
    from service.settings import Settings
    from service.timeouts import uvicorn_options

    if args.workers is not None and args.workers < 1:
        raise InputError("workers", f"must be at least 1, got {args.workers}")
    if args.queue_size is not None and args.queue_size < 1:
        raise InputError("queue-size", f"must be at least 1, got {args.queue_size}")
    if not 0 <= args.port <= 65535:
        raise InputError("port", f"must lie in [0, 65535], got {args.port}")
    try:
        settings = Settings.from_env(data_dir=args.data_dir, workers=args.workers, queue_size=args.queue_size,
                                     executor=args.ray and "ray", executor_address=args.ray)
    except ValidationError as exc:
        error = exc.errors()[0]
        name = str(error["loc"][0]) if error["loc"] else "settings"
        raise InputError(name, f"{error['msg']} (the flag or PHD_{name.upper()}), got {error.get('input')!r}") from None
    app = create_app(settings)
    # Python warnings (a library's, issued inside a request) go to the log like everything else
    # the server says, not to the `phd` command's printer: a log write that fails (a full disk)
    # is dropped by logging, never raised into the request.
    logging.captureWarnings(True)
    app.state.service.executor.connect()    # a cluster that cannot be reached: a start-up error naming it
    where = settings.executor + (f" at {settings.executor_address}" if settings.executor_address else "")
    base = f"http://{page_host(args.host)}:{args.port}"
    print(f"phd serve: the page: {base}/ui/  (REST API docs: {base}/docs)", flush=True)
    print(f"phd serve: data in {settings.data_dir}, {settings.workers} worker(s), queue {settings.queue_size}, "
          f"compute {where}, API key {'required' if settings.api_key else 'off'}", flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level, **uvicorn_options(settings))
    return 0


def page_host(host: str) -> str:
    """Where a browser on this machine reaches a server bound to `host` (all addresses: 127.0.0.1)."""
    if host in ("0.0.0.0", "", "::"):
        return "127.0.0.1"
    return f"[{host}]" if ":" in host else host
