"""Real processes on loopback for the fleet bench and the tests: `cloudtrack-backend serve` replicas,
Debian's `redis-server` and `nginx` as a load balancer, each on a free port, stopped with the context manager.

Redis runs with `appendonly yes` / `appendfsync always`: a write it acknowledged is on disk. nginx passes
a request to the next replica when one is down (`proxy_next_upstream`), so killing a replica mid-run
costs the clients nothing but a retry they never see; Server-Sent Events pass unbuffered.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import TracebackType

import requests

REDIS_SERVER = "/usr/bin/redis-server"
NGINX = "/usr/sbin/nginx"


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def _wait_for_port(port: int, process: subprocess.Popen[bytes], what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"{what} exited with status {process.returncode}")
        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise RuntimeError(f"{what} did not listen on port {port} within {timeout_s:.0f} s")


class _Service:
    def __init__(self) -> None:
        self.port = free_port()
        self.folder = Path(tempfile.mkdtemp(prefix="cloudtrack-"))
        self._process: subprocess.Popen[bytes] | None = None

    def stop(self) -> None:
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait(timeout=10)
        shutil.rmtree(self.folder, ignore_errors=True)

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


class RedisServer(_Service):
    """`redis-server` on 127.0.0.1:<free port>, persistence to an append-only file fsync'd on every write."""

    def __init__(self, binary: str = REDIS_SERVER) -> None:
        super().__init__()
        if not Path(binary).exists():
            raise RuntimeError(f"{binary} is missing: install Debian's redis-server (make install-services)")
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self._command = [
            binary,
            "--bind",
            "127.0.0.1",
            "--port",
            str(self.port),
            "--dir",
            str(self.folder),
            "--save",
            "",
            "--appendonly",
            "yes",
            "--appendfsync",
            "always",
            "--protected-mode",
            "yes",
            "--daemonize",
            "no",
            "--loglevel",
            "warning",
            "--maxmemory",
            "256mb",
        ]

    def start(self) -> RedisServer:
        self._process = subprocess.Popen(self._command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        _wait_for_port(self.port, self._process, "redis-server")
        return self

    def __enter__(self) -> RedisServer:
        return self.start()


NGINX_CONF = """daemon off;
worker_processes 1;
pid {folder}/nginx.pid;
error_log {folder}/error.log warn;
events {{ worker_connections 1024; }}
http {{
    access_log off;
    client_body_temp_path {folder}/body;
    proxy_temp_path {folder}/proxy;
    fastcgi_temp_path {folder}/fastcgi;
    uwsgi_temp_path {folder}/uwsgi;
    scgi_temp_path {folder}/scgi;
    client_max_body_size 4m;
    client_body_buffer_size 4m;  # bodies stay in memory: no temp files for a worker user to write
    upstream backend {{
{servers}
        keepalive 32;
    }}
    server {{
        listen 127.0.0.1:{port};
        location / {{
            proxy_pass http://backend;
            proxy_http_version 1.1;
            proxy_set_header Connection "";
            proxy_set_header Host $host;
            proxy_set_header X-Forwarded-For $proxy_add_x_forwarded_for;
            proxy_connect_timeout 2s;
            proxy_read_timeout 120s;
            # A replica that died: try the next one, also for POSTs (the store makes a retried write safe
            # to repeat: a status is replaced, a detection has no side effect but its candidates).
            proxy_next_upstream error timeout non_idempotent;
            proxy_next_upstream_tries 2;
            proxy_buffering off;
        }}
    }}
}}
"""


class NginxBalancer(_Service):
    """nginx on 127.0.0.1:<free port> balancing over `upstreams` (base URLs such as http://127.0.0.1:8081)."""

    def __init__(self, upstreams: list[str], binary: str = NGINX) -> None:
        super().__init__()
        if not Path(binary).exists():
            raise RuntimeError(f"{binary} is missing: install Debian's nginx (make install-services)")
        self.url = f"http://127.0.0.1:{self.port}"
        servers = "\n".join(
            f"        server {u.removeprefix('http://')} max_fails=1 fail_timeout=10s;" for u in upstreams
        )
        self.folder.chmod(0o755)  # started as root, nginx's workers run as another user
        self.config = self.folder / "nginx.conf"
        self.config.write_text(NGINX_CONF.format(folder=self.folder, servers=servers, port=self.port))
        self._binary = binary

    def start(self) -> NginxBalancer:
        self._process = subprocess.Popen(
            [
                self._binary,
                "-c",
                str(self.config),
                "-p",
                str(self.folder),
                "-e",
                str(self.folder / "error.log"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        _wait_for_port(self.port, self._process, "nginx")
        return self

    def __enter__(self) -> NginxBalancer:
        return self.start()


class BackendProcess:
    """`cloudtrack-backend serve` in a child process on a free loopback port; `kill()` is a SIGKILL."""

    def __init__(
        self,
        settings: list[str],
        tokens: dict[str, str],
        supervisor_token: str = "",
        port: int | None = None,
        source_tree: Path | None = None,
    ) -> None:
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "CLOUDTRACK_BACKEND_AUTH__TOKENS": json.dumps(tokens)}
        if source_tree is not None:  # another version of the code (a bench's "before"), first on the path
            env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(source_tree), env.get("PYTHONPATH")]))
        if supervisor_token:
            env["CLOUDTRACK_BACKEND_AUTH__SUPERVISOR_TOKEN"] = supervisor_token
        flags = [arg for s in [f"server.port={self.port}", *settings] for arg in ("--set", s)]
        # A file, not a pipe nobody reads: a chatty server must never block on a full pipe.
        self._log = tempfile.TemporaryFile()  # noqa: SIM115 - closed in stop()
        self._process = subprocess.Popen(
            [sys.executable, "-m", "backend.cli", "--log-level", "WARNING", "serve", *flags],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=self._log,
            cwd=source_tree,  # `python -m` puts its working directory first: there, that tree is found first
        )

    def log_tail(self) -> str:
        self._log.seek(0)
        return self._log.read().decode(errors="replace").strip()[-800:]

    @property
    def pid(self) -> int:
        return self._process.pid

    def wait_ready(self, timeout_s: float = 60.0) -> BackendProcess:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                raise RuntimeError(f"the back-end exited: {self.log_tail()}")
            try:
                if requests.get(self.url + "/health", timeout=1).ok:
                    return self
            except requests.RequestException:
                pass
            time.sleep(0.2)
        raise RuntimeError("the back-end did not become healthy")

    def rss_bytes(self) -> int:
        """Resident memory of the server process, from /proc."""
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        raise RuntimeError("no VmRSS for the back-end process")

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs, as in a crash or an OOM kill."""
        if self._process.poll() is None:
            self._process.send_signal(signal.SIGKILL)
        self._process.wait(timeout=10)

    def stop(self) -> None:
        if self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait(timeout=10)
        self._log.close()

    def __enter__(self) -> BackendProcess:
        return self.wait_ready()

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
