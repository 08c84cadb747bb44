"""Run the service in a background thread of the current process (demo, benchmark, tests).

    with BackgroundServer(Settings(data_dir=...)) as server:
        PHDClient(server.url).health()

Port 0 (the default) lets the OS pick a free port; `url` has the real one.
"""

from __future__ import annotations

import threading
import time

import uvicorn

from .app import create_app
from .settings import Settings
from .timeouts import uvicorn_options


class BackgroundServer:
    def __init__(self, settings: Settings, *, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning",
                 start_timeout: float = 30.0):
        self.settings = settings
        self.app = create_app(settings)
        config = uvicorn.Config(self.app, host=host, port=port, log_level=log_level, lifespan="on",
                                **uvicorn_options(settings))
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="phd-service", daemon=True)
        self.thread.start()
        deadline = time.monotonic() + start_timeout
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"the service did not start on {host}:{port}")
            time.sleep(0.01)
        self.port = self.server.servers[0].sockets[0].getsockname()[1]
        self.url = f"http://{host}:{self.port}"

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=60)

    def __enter__(self) -> "BackgroundServer":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
