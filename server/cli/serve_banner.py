"""What ``burrforce serve`` prints once it is ready: the endpoints, the key, where the token
is, and commands to try, each runnable as printed."""

from __future__ import annotations

from pathlib import Path

from ...client import connection
from ..api.config import TOKEN_FILE, ServeConfig
from .invocation import burrforce_command


def say_banner(say, elapsed_s: float, url: str, c: connection.Connection, token: str,
            new_token: bool, config: ServeConfig, conn_path: Path,
            haptic_device: str | None = None, pool: str | None = None) -> None:
    say(f"ready in {elapsed_s:.1f} s")
    output = f"coupled output (device {config.device})" if config.device else "raw force"
    bound = config.host if config.host in ("0.0.0.0", "::") else c.host
    say(f"  UDP   {bound}:{c.udp_port}  session {c.session}, frame {c.frame}, {output}, "
        + (f"key {c.key_hex}" if c.key_hex else "no key (untagged datagrams)"))
    if pool:
        say(f"  {pool}")
    say(f"  REST  {url}/v1   (OpenAPI docs: {url}/docs)")
    # The fragment never reaches the server or its logs; the page keeps the token for the
    # tab and drops it from the address bar. A token not shown now stays out of the link.
    say(f"  VIEW  {ui_link(url, token if new_token else None)}   (live view in a browser)")
    if new_token:
        say(f"  token {token}   (new: shown only now; kept in "
            f"{Path(config.data_dir).expanduser() / TOKEN_FILE})")
    elif config.token:
        say("  token as configured")
    else:
        say(f"  token in {Path(config.data_dir).expanduser() / TOKEN_FILE}")
    say(f"  connection file {conn_path}")
    if haptic_device:
        say(f"  DEVICE {haptic_device} streams session {c.session}   (status: GET "
            f"{url}/v1/sessions/{c.session}/device)")
    token_hint = ("TOKEN=<the configured token>" if config.token else
                  f"TOKEN=$(cat {Path(config.data_dir).expanduser() / TOKEN_FILE})")
    if haptic_device:  # a second stream on the device's session would fight it
        say(f"try:  {token_hint}")
    else:
        say(f"try:  {burrforce_command()} client demo          (cuts a groove and prints the "
            "forces)")
        say(f"      {token_hint}")
    say(f"      curl -H \"Authorization: Bearer $TOKEN\" -X PATCH -H 'Content-Type: "
        f"application/json' -d '{{\"us_n_mm2\": 1610}}' {url}/v1/sessions/{c.session}/"
        "parameters")
    say(f"      curl -H \"Authorization: Bearer $TOKEN\" -o bone.stl "
        f"{url}/v1/sessions/{c.session}/export/mesh")
    say("Ctrl-C stops the server.")


def pool_line(plane, session) -> str | None:
    """With several workers: their ports, and which one the default session is on."""
    workers = plane.workers
    if len(workers) < 2:
        return None
    ports = ", ".join(str(h.address[1]) if h.address else "?" for h in workers)
    return (f"POOL  {len(workers)} hot-loop workers on UDP ports {ports}; session "
            f"{session.id} is on worker {session.worker} (each session's port: GET "
            "/v1/sessions/ID → udp)")


def ui_link(url: str, token: str | None) -> str:
    """The live view's address, with the token in the fragment when it may be shown."""
    return f"{url}/ui/" + (f"#token={token}" if token else "")
