"""podman as the container engine for the image's tests and the project's container benchmark
(``python -m benchmarks.container``).

Docker's engine cannot run on every machine that must build the image (CI's has none);
podman builds the same Dockerfile daemonless, as root or rootless. What a sandboxed machine
needs is written into a containers.conf of our own (``CONTAINERS_CONF``), never into the
machine's:

- the containers get this process's own file and process limits (the latter at most
  podman's default): a sandbox may forbid raising them, and runc then fails at
  ``setrlimit``;
- runc where it is installed (crun, podman's default on Debian, fails in cgroup v1/hybrid
  sandboxes), cgroupfs where systemd is not running, events to a file instead of journald.

The base image comes from a registry where one is reachable (``BASE``), else from Debian's
archive through mmdebstrap, imported as ``localhost/burrforce-base:bookworm``: no registry.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

#: The locally made base: Debian's python3 (3.11 on bookworm) with venv, and CA roots.
BASE_IMAGE = "localhost/burrforce-base:bookworm"
BASE_PACKAGES = ("python3", "python3-venv", "ca-certificates")
#: Documentation and translations are never read in a server image.
BASE_EXCLUDES = ("/usr/share/doc/*", "/usr/share/man/*", "/usr/share/info/*",
                 "/usr/share/locale/*")
#: Where a machine whose TLS is re-signed by a private CA keeps its roots: mounted into
#: the build so pip inside it can reach PyPI (harmless elsewhere).
CA_BUNDLE = Path("/etc/ssl/certs/ca-certificates.crt")
#: The image's ports and its user.
UDP_PORT = 47810
HTTP_PORT = 47811
IMAGE_USER = "10001:10001"


class PodmanError(RuntimeError):
    """A podman command failed; the message holds its output."""


def cache_dir() -> Path:
    """$BURRFORCE_CONTAINER_CACHE, else ~/.cache/burrforce/container: the base image's tar."""
    env = os.environ.get("BURRFORCE_CONTAINER_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "burrforce" / "container"


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port free on 127.0.0.1 now (UDP or TCP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: podman's own default process limit: a sandbox may refuse more even when this process's
#: limit is higher (seen here: 32768 is set, 65536 is "operation not permitted").
PODMAN_NPROC = 32768


def _limit(which: int, cap: int | None = None) -> str:
    soft, hard = resource.getrlimit(which)
    unlimited = resource.RLIM_INFINITY
    hard_v = 1 << 20 if hard == unlimited else hard
    soft_v = hard_v if soft == unlimited else soft
    if cap is not None:
        hard_v, soft_v = min(hard_v, cap), min(soft_v, cap)
    return f"{soft_v}:{hard_v}"


def _limits() -> dict[str, str]:
    return {"nofile": _limit(resource.RLIMIT_NOFILE),
            "nproc": _limit(resource.RLIMIT_NPROC, PODMAN_NPROC)}


def containers_conf() -> str:
    """The containers.conf this machine needs (see the module's docstring)."""
    lines = ["[containers]",
             "default_ulimits = [" + ", ".join(f'"{k}={v}"' for k, v in _limits().items())
             + "]",
             "[engine]", 'events_logger = "file"']
    if shutil.which("runc"):
        lines.append('runtime = "runc"')
    if not Path("/run/systemd/system").is_dir():
        lines.append('cgroup_manager = "cgroupfs"')
    return "\n".join(lines) + "\n"


def compose_ulimits() -> dict:
    """The same limits in a compose file's ``ulimits:`` form (compose's containers, created
    over the Docker API, do not get containers.conf's defaults), and this process's own nice
    and real-time priority limits in place of docker/compose.yaml's 30 and 5, which a sandbox
    may refuse to raise to (podman passes compose's SYS_NICE on to the image's user, which
    allows both)."""
    out = {}
    limits = {**_limits(), "nice": _limit(resource.RLIMIT_NICE),
              "rtprio": _limit(resource.RLIMIT_RTPRIO)}
    for name, value in limits.items():
        soft, hard = (int(v) for v in value.split(":"))
        out[name] = {"soft": soft, "hard": hard}
    return out


@dataclass
class Podman:
    """podman with our containers.conf (written under ``conf_dir``)."""

    conf_dir: Path
    env: dict = field(init=False)

    def __post_init__(self) -> None:
        self.conf_dir.mkdir(parents=True, exist_ok=True)
        conf = self.conf_dir / "containers.conf"
        conf.write_text(containers_conf())
        self.env = {**os.environ, "CONTAINERS_CONF": str(conf)}

    def __call__(self, *args: str, timeout_s: float = 120.0, check: bool = True,
                 capture: bool = True) -> subprocess.CompletedProcess:
        try:
            r = subprocess.run(["podman", *args], env=self.env, timeout=timeout_s, text=True,
                               capture_output=capture)
        except subprocess.TimeoutExpired as exc:
            raise PodmanError(f"podman {' '.join(args)}: no answer in {timeout_s:g} s") from exc
        if check and r.returncode != 0:
            raise PodmanError(f"podman {' '.join(args)} exited {r.returncode}:\n"
                              f"{(r.stdout or '')[-3000:]}{(r.stderr or '')[-3000:]}")
        return r

    def unavailable(self) -> str | None:
        """Why podman cannot run containers here, or None: installed, and a container runs."""
        if shutil.which("podman") is None:
            return "podman is not installed (Debian: apt-get install podman runc)"
        try:
            self("info", timeout_s=60.0)
        except PodmanError as exc:
            return f"podman cannot run here: {exc}"
        return None

    def image_exists(self, ref: str) -> bool:
        return self("image", "exists", ref, check=False).returncode == 0

    def image_size_bytes(self, ref: str) -> int:
        """The image's size, all layers uncompressed (what it takes on disk)."""
        return int(self("image", "inspect", "--format", "{{.Size}}", ref).stdout.strip())

    def inspect(self, ref: str, kind: str = "image") -> dict:
        return json.loads(self(kind, "inspect", ref).stdout)[0]

    def base_image(self, cache: Path | None = None, progress=None) -> tuple[str, float]:
        """``BASE_IMAGE``, imported from a cached tar or made by mmdebstrap first; returns it
        and the seconds it took (0 when it was there).

        Raises:
            PodmanError: mmdebstrap is missing or failed.
        """
        say = progress or (lambda text: None)
        if self.image_exists(BASE_IMAGE):
            return BASE_IMAGE, 0.0
        t0 = time.monotonic()
        cache = cache or cache_dir()
        cache.mkdir(parents=True, exist_ok=True)
        tar = cache / ("bookworm-" + "-".join(BASE_PACKAGES) + ".tar")
        if not tar.exists():
            if shutil.which("mmdebstrap") is None:
                raise PodmanError("no base image: mmdebstrap is not installed "
                                  "(Debian: apt-get install mmdebstrap)")
            say(f"making the base image from Debian's archive (mmdebstrap) into {tar}")
            partial = tar.with_suffix(".partial.tar")
            cmd = ["mmdebstrap", "--quiet", "--variant=minbase",
                   "--include=" + ",".join(BASE_PACKAGES),
                   *(f"--dpkgopt=path-exclude={p}" for p in BASE_EXCLUDES),
                   "bookworm", str(partial)]
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
            if r.returncode != 0:
                raise PodmanError(f"mmdebstrap exited {r.returncode}:\n{r.stderr[-3000:]}")
            partial.rename(tar)
        self("import", str(tar), BASE_IMAGE, timeout_s=300.0)
        return BASE_IMAGE, time.monotonic() - t0

    def build(self, tag: str, context: Path, base: str | None = None,
              dockerfile: str = "docker/Dockerfile", layer_cache: bool = True,
              also: tuple[str, ...] = ()) -> float:
        """``podman build`` of ``dockerfile`` in ``context`` as ``tag`` and the names in
        ``also`` (docker format: OCI images drop HEALTHCHECK); every layer anew unless
        ``layer_cache``; returns its wall time, s."""
        args = ["build", "--format", "docker", "--network", "host", "-f",
                str(context / dockerfile), "-t", tag]
        for name in also:
            args += ["-t", name]
        if not layer_cache:
            args.append("--no-cache")
        if base is not None:
            args += ["--pull=never", "--build-arg", f"BASE={base}"]
        if CA_BUNDLE.is_file():
            args += ["-v", f"{CA_BUNDLE}:{CA_BUNDLE}:ro"]
        t0 = time.monotonic()
        self(*args, str(context), timeout_s=1800.0)
        return time.monotonic() - t0

    def run(self, image: str, name: str, env: dict[str, str] | None = None,
            publish: tuple[str, ...] = (), network: str | None = None,
            args: tuple[str, ...] = (), command: tuple[str, ...] = ()) -> Container:
        """``podman run -d`` (removed first if a container of that name is left over)."""
        Container(self, name).remove()
        opts = ["run", "-d", "--name", name, "--shm-size", "1g"]
        for k, v in (env or {}).items():
            opts += ["-e", f"{k}={v}"]
        for p in publish:
            opts += ["-p", p]
        if network is not None:
            opts += ["--network", network]
        self(*opts, *args, image, *command)
        return Container(self, name)


@dataclass
class Container:
    """A container started by :meth:`Podman.run` (or by compose, by name)."""

    podman: Podman
    name: str

    def logs(self) -> str:
        r = self.podman("logs", self.name, check=False)
        return (r.stdout or "") + (r.stderr or "")

    def exec(self, *cmd: str, timeout_s: float = 60.0) -> str:
        return self.podman("exec", self.name, *cmd, timeout_s=timeout_s).stdout

    def state(self) -> dict:
        return self.podman.inspect(self.name, "container")["State"]

    def wait_http(self, url: str, timeout_s: float = 180.0, status: int = 200) -> float:
        """Wait until GET ``url`` answers ``status``; returns the seconds waited.

        Raises:
            PodmanError: the container stopped, or no such answer in time (with its log).
        """
        import httpx

        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            try:
                if httpx.get(url, timeout=2.0).status_code == status:
                    return time.monotonic() - t0
            except httpx.HTTPError:
                pass
            state = self.state()
            if not state.get("Running", False) and \
                    state.get("Status") not in ("created", "configured"):
                break
            time.sleep(0.25)
        raise PodmanError(f"{url} did not answer {status} in {timeout_s:g} s; "
                          f"container {self.name}: {self.state().get('Status')}; its log:\n"
                          f"{self.logs()[-4000:]}")

    def stop(self, timeout_s: int = 20) -> int:
        """SIGTERM, then SIGKILL after ``timeout_s``; returns the exit code."""
        self.podman("stop", "--time", str(timeout_s), self.name, timeout_s=timeout_s + 30.0)
        return int(self.state()["ExitCode"])

    def remove(self) -> None:
        """Remove it and its anonymous volumes (the image declares /data one)."""
        self.podman("rm", "--force", "--ignore", "--volumes", self.name, check=False)
