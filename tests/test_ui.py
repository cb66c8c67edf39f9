"""The live view, /ui/, in headless Debian chromium against the real stack (hot loop, uvicorn
on 127.0.0.1), with every other host refused: the page asks for the token and refuses a wrong
one; while a client streams a groove over UDP its plots update and the 3D view changes where
the groove is cut; the report of a recording shows the volume the recording removed; the
controls change the session over REST and show the server's errors."""

from __future__ import annotations

import base64
import hashlib
import io
import re
import threading
import time
from collections.abc import Iterator
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest
from browser import LOOPBACK, RENDER_TIMEOUT_MS, WEBGL_ARGS, OfflinePage, chromium
from PIL import Image

from burrforce.client.udp import BurrClient, ServerGone
from burrforce.proto.mesh_chunks import decode
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.models import Parameters
from burrforce.server.api.stack import ServerStack

TOKEN = "ui-test-token-0123456789abcdef"
SID = 7
RADIUS_MM = 2.0
DEPTH_MM = 0.5
#: Half the groove's width at the workpiece's top face (z = 0), mm.
HALF_WIDTH_MM = float(np.sqrt(RADIUS_MM ** 2 - (RADIUS_MM - DEPTH_MM) ** 2))
URL = re.compile(r"""https?://[^\s"'<>()]+""")


@pytest.fixture(scope="module")
def stack(tmp_path_factory) -> Iterator[ServerStack]:
    config = ServeConfig(http_port=0, udp_port=0, workers=1,
                         data_dir=tmp_path_factory.mktemp("ui-data"))
    with ServerStack(config, TOKEN, journal=False) as st:
        source = st.plane.resolve("phantom:workpiece", None, 0.2)
        st.add_session(source, Parameters(), session_id=SID)
        yield st


@pytest.fixture(scope="module")
def browser() -> Iterator:
    with chromium(WEBGL_ARGS) as b:
        yield b


@pytest.fixture
def offline(browser) -> Iterator[OfflinePage]:
    page = OfflinePage(browser, viewport={"width": 1400, "height": 850})
    try:
        yield page
    finally:
        page.close()


def rest(stack) -> httpx.Client:
    return httpx.Client(base_url=stack.url + "/v1", timeout=30.0,
                        headers={"Authorization": f"Bearer {TOKEN}"})


def stream_groove(stack, x0_mm: float, x1_mm: float, y_mm: float, seconds: float) -> dict:
    """Cut a groove 0.5 mm deep along +x at 1 kHz (60 000 rpm, burr upright); the last
    reply's bone version and how many replies came."""
    session = stack.plane.get(SID)
    n = int(seconds * 1000)
    last = None
    answered = 0
    with BurrClient(*stack.udp_address, session.id, session.key_hex) as client:
        start = time.monotonic()
        for i in range(n):
            x = x0_mm + (x1_mm - x0_mm) * i / (n - 1)
            try:
                last = client.exchange((x, y_mm, RADIUS_MM - DEPTH_MM), rpm=60000.0,
                                       timeout_s=0.5).reply
                answered += 1
            except (TimeoutError, ServerGone):
                continue
            pause = start + (i + 1) * 1e-3 - time.monotonic()
            if pause > 0:
                time.sleep(pause)
    assert last is not None
    return {"bone_version": last.bone_version, "answered": answered}


def open_view(offline: OfflinePage, stack, token: str | None = TOKEN) -> None:
    page = offline.page
    page.goto(stack.url + "/ui/" + (f"#token={token}" if token else ""), wait_until="load")
    if token:
        page.wait_for_function(
            f"() => window.burrforceView && burrforceView.state.selected === {SID} "
            "&& burrforceView.state.copy && burrforceView.state.copy.have !== null "
            "&& burrforceView.scene.frames > 0", timeout=RENDER_TIMEOUT_MS)


def view_image(page) -> np.ndarray:
    """The 3D view as pixels (rows, columns, RGB) once a frame newer than now is drawn."""
    frames = page.evaluate("() => burrforceView.scene.frames")
    page.evaluate("() => burrforceView.scene.invalidate()")
    page.wait_for_function(f"() => burrforceView.scene.frames > {frames}",
                           timeout=RENDER_TIMEOUT_MS)
    png = page.locator("#view canvas").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def test_the_page_is_served_with_its_scripts_and_a_self_only_policy(stack):
    with httpx.Client(base_url=stack.url, timeout=30.0) as anon:
        r = anon.get("/ui", follow_redirects=False)
        assert r.status_code == 307 and r.headers["location"] == "/ui/"
        page = anon.get("/ui/")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert [u for u in URL.findall(page.text) if urlsplit(u).hostname not in LOOPBACK] == []
        policy = page.headers["content-security-policy"]
        assert "default-src 'none'" in policy and "https:" not in policy and "*" not in policy
        # The inline import map is allowed by its hash, and nothing else inline.
        inline = re.findall(r"<script type=\"importmap\">(.*?)</script>", page.text, re.S)
        digest = base64.b64encode(hashlib.sha256(inline[0].encode()).digest()).decode()
        directives = {d.split()[0]: d.split()[1:] for d in policy.split(";") if d.strip()}
        assert directives["script-src"] == ["'self'", f"'sha256-{digest}'"]
        # Every file the page and its modules load is served, without a token.
        assets = re.findall(r"(?:src|href)=\"((?:static|vendor)/[^\"]+)\"", page.text)
        assets += ["vendor/three/three.module.js", "vendor/three/three.core.js",
                   "vendor/three/OrbitControls.js", "static/api.js", "static/mesh.js",
                   "static/plots.js", "static/scene.js", "static/controls.js"]
        for path in assets:
            got = anon.get("/ui/" + path)
            assert got.status_code == 200, path
            if path.endswith(".js"):
                assert got.headers["content-type"].startswith("text/javascript"), path
        assert anon.get("/ui/static/%2e%2e/%2e%2e/v1/sessions").status_code == 404
        assert anon.get("/ui/static/nothing.js").status_code == 404
        # The page only at /ui/, with its policy: not as a static file without one.
        assert anon.get("/ui/static/index.html").status_code == 404
        # The data stays behind the token.
        assert anon.get("/v1/sessions").status_code == 401
        assert not any(p.startswith("/ui") for p in anon.get("/openapi.json").json()["paths"])


def test_views_carry_what_the_page_draws(stack):
    with rest(stack) as api:
        view = api.get(f"/sessions/{SID}").json()
        assert view["device"] is None and view["device_attached"] is False
        params = api.get(f"/sessions/{SID}/parameters").json()
    profile = np.asarray(params["burr_profile_mm"])
    # The round burr's generatrix: tip (0, -R) to top (0, R), on the sphere.
    assert profile[0] == pytest.approx([0.0, -RADIUS_MM]) and profile[-1] == pytest.approx(
        [0.0, RADIUS_MM])
    assert np.hypot(profile[:, 0], profile[:, 1]) == pytest.approx(RADIUS_MM, abs=1e-3)


def test_the_page_asks_for_the_token_and_refuses_a_wrong_one(stack, offline):
    page = offline.page
    offline.expected_http = {(401, "/v1/sessions")}
    open_view(offline, stack, token=None)
    page.locator("#login").wait_for(state="visible", timeout=RENDER_TIMEOUT_MS)
    assert page.locator("#main").is_hidden()
    assert "token" in page.locator("#login-reason").inner_text()
    # Where the token is kept, as the server's 401 says it.
    assert str(stack.config.data_dir / "token") in page.locator("#login-reason").inner_text()
    page.fill("#token", "not-the-token-0123456789")
    page.click("#login-form button[type=submit]")
    page.wait_for_function("() => document.getElementById('login-reason').textContent"
                           ".includes('401')", timeout=RENDER_TIMEOUT_MS)
    assert page.locator("#main").is_hidden()
    assert page.locator("#sessions-body tr").count() == 0
    page.fill("#token", TOKEN)
    page.click("#login-form button[type=submit]")
    page.locator(f"#sessions-body tr[data-session='{SID}']").wait_for(timeout=RENDER_TIMEOUT_MS)
    assert page.locator("#login").is_hidden()
    # Kept for the tab: a reload needs no token again; "Forget token" drops it.
    page.reload(wait_until="load")
    page.locator(f"#sessions-body tr[data-session='{SID}']").wait_for(timeout=RENDER_TIMEOUT_MS)
    page.click("#logout")
    page.locator("#login").wait_for(state="visible", timeout=RENDER_TIMEOUT_MS)
    assert page.evaluate("() => sessionStorage.length") == 0
    offline.check()


def test_plots_update_and_the_groove_shows_in_3d_while_a_client_streams(stack, offline):
    page = offline.page
    open_view(offline, stack)
    # The token left the address bar (and the history) at once.
    assert "token" not in page.evaluate("() => window.location.href")
    x0, x1, y = 6.0, 14.0, -4.0  # the workpiece spans x 0…26, y −8…8 mm; top z = 0
    page.uncheck("#show-burr")  # only the bone's pixels are compared
    page.evaluate("() => { document.getElementById('readout').hidden = true; }")
    page.evaluate(f"() => burrforceView.scene.lookDownAt([{(x0 + x1) / 2}, {y}, 0], 24)")
    before = view_image(page)
    samples_before = page.evaluate("() => burrforceView.plots.samples")
    frames_before = page.evaluate("() => burrforceView.scene.frames")

    result: dict = {}
    cutter = threading.Thread(target=lambda: result.update(
        stream_groove(stack, x0, x1, y, seconds=2.5)))
    cutter.start()
    seen = []
    while cutter.is_alive():
        seen.append(page.evaluate("() => burrforceView.plots.samples"))
        page.wait_for_timeout(400)
    cutter.join()
    assert result["answered"] >= 2400
    # Pushed while the groove was being cut, at the page's 30 Hz, not only at the end.
    assert seen[-1] - samples_before >= 30, seen
    assert len(set(seen)) >= 4, seen
    force = page.evaluate("() => burrforceView.plots.charts[0].data[1]")
    assert max(f for f in force if f is not None) > 0.5  # N: a 0.5 mm cut at 3 mm/s
    # The 3D view followed too: at least 2 frames a second even on a software renderer.
    assert page.evaluate("() => burrforceView.scene.frames") - frames_before >= 4

    page.wait_for_function(
        f"() => burrforceView.state.copy.have >= {result['bone_version']}",
        timeout=RENDER_TIMEOUT_MS)
    after = view_image(page)
    assert after.shape == before.shape
    changed = np.abs(after - before).sum(axis=2) > 24
    # Where the groove is on screen: its top-face outline projected by the page's camera.
    corners = [[x, yy, z] for x in (x0 - HALF_WIDTH_MM, x1 + HALF_WIDTH_MM)
               for yy in (y - HALF_WIDTH_MM, y + HALF_WIDTH_MM) for z in (0.0, -DEPTH_MM)]
    px = np.array(page.evaluate(
        """(corners) => { const s = burrforceView.scene; const c = s.renderer.domElement;
             return corners.map(([x, y, z]) => { const v = s.camera.position.clone().set(x, y, z)
               .project(s.camera); return [(v.x + 1) / 2 * c.clientWidth,
                                           (1 - v.y) / 2 * c.clientHeight]; }); }""",
        corners))
    scale = after.shape[1] / page.evaluate("() => burrforceView.scene.renderer.domElement"
                                           ".clientWidth")
    (c0, r0), (c1, r1) = np.floor(px.min(axis=0) * scale) - 3, np.ceil(px.max(axis=0) * scale) + 3
    inside = np.zeros_like(changed)
    inside[max(int(r0), 0):int(r1), max(int(c0), 0):int(c1)] = True
    assert inside.sum() > 2000  # the groove is large on screen
    share_inside = changed[inside].mean()
    share_outside = changed[~inside].mean()
    assert share_inside > 0.25, (share_inside, share_outside)
    assert share_outside < 0.01, (share_inside, share_outside)
    offline.check()


def test_the_report_of_a_recording_shows_the_volume_it_removed(stack, offline):
    with rest(stack) as api:
        before = sum(api.get(f"/sessions/{SID}/state").json()["removed_mm3"].values())
        r = api.post(f"/sessions/{SID}/recording", json={"name": "ui-groove"})
        assert r.status_code in (200, 201), r.text
        stream_groove(stack, 16.0, 20.0, 4.0, seconds=1.2)
        assert api.delete(f"/sessions/{SID}/recording").status_code == 200
        removed = sum(api.get(f"/sessions/{SID}/state").json()["removed_mm3"].values()) - before
        report = api.get("/recordings/ui-groove.burrrec/report").json()
    assert removed > 5.0  # mm³: 4 mm of a 0.5 mm deep groove of a 4 mm burr and its ends
    assert report["removed_mm3"] == pytest.approx(removed, rel=0.01)

    page = offline.page
    open_view(offline, stack)
    page.click("details[data-part=recording] > summary")
    page.locator("#recording-list option[value='ui-groove.burrrec']").wait_for(
        state="attached", timeout=RENDER_TIMEOUT_MS)
    page.select_option("#recording-list", "ui-groove.burrrec")
    with offline.context.expect_page(timeout=RENDER_TIMEOUT_MS) as popup:
        page.click("details[data-part=recording] button:has-text('Report')")
    shown = popup.value
    shown.wait_for_load_state("load")
    card = shown.locator(".card", has_text="Bone removed").inner_text()
    value = float(re.search(r"([0-9.]+)\s*mm³", card).group(1))
    assert value == pytest.approx(removed, rel=0.005)  # shown to 3 significant digits
    offline.check()


def test_controls_change_the_session_and_show_the_servers_refusal(stack, offline):
    page = offline.page
    offline.expected_http = {(422, f"/v1/sessions/{SID}/parameters")}
    open_view(offline, stack)
    page.locator("#p-us_n_mm2").wait_for(timeout=RENDER_TIMEOUT_MS)
    page.fill("#p-us_n_mm2", "-5")
    page.click("#parameters-form button[type=submit]")
    page.wait_for_function("() => document.getElementById('parameters-status').textContent"
                           ".includes('422')", timeout=RENDER_TIMEOUT_MS)
    assert "us_n_mm2" in page.locator("#parameters-status").inner_text()
    with rest(stack) as api:
        try:
            _change_parameters_and_materials(page, api)
        finally:  # the module's other tests share the session
            api.patch(f"/sessions/{SID}/parameters",
                      json={"us_n_mm2": 805.1}).raise_for_status()
            api.patch(f"/sessions/{SID}/materials/1",
                      json={"forbidden": False}).raise_for_status()
    offline.check()


def _change_parameters_and_materials(page, api: httpx.Client) -> None:
    """Us through the parameters form; material 1 marked forbidden in the materials table."""
    assert api.get(f"/sessions/{SID}/parameters").json()["us_n_mm2"] == 805.1
    page.fill("#p-us_n_mm2", "1610")
    page.click("#parameters-form button[type=submit]")
    page.wait_for_function("() => document.getElementById('parameters-status')"
                           ".textContent.includes('done')", timeout=RENDER_TIMEOUT_MS)
    assert api.get(f"/sessions/{SID}/parameters").json()["us_n_mm2"] == 1610.0
    # A material marked forbidden is drawn through the bone, from its own surface.
    assert page.evaluate("() => burrforceView.scene.forbidden.visible") is False
    page.click("details[data-part=materials] > summary")
    row = page.locator("table.materials tr[data-label='1']")
    row.locator("input[type=checkbox]").check()
    row.locator("button").click()
    page.wait_for_function("() => document.getElementById('materials-status')"
                           ".textContent.includes('done')", timeout=RENDER_TIMEOUT_MS)
    assert api.get(f"/sessions/{SID}/materials").json()[0]["forbidden"] is True
    page.wait_for_function(
        "() => burrforceView.scene.forbidden.visible && burrforceView.scene.forbidden"
        ".geometry.getAttribute('position').count > 1000", timeout=RENDER_TIMEOUT_MS)


def test_the_pages_mesh_reader_agrees_with_the_protocols_and_refuses_bad_messages(
        stack, offline):
    with rest(stack) as api:
        r = api.get(f"/sessions/{SID}/mesh", params={"format_version": 2, "frame": "server",
                                                     "max_bytes": 64 << 20})
        assert r.status_code == 200
    expected = decode(r.content)
    page = offline.page
    open_view(offline, stack)
    got = page.evaluate(
        """async ([token, sid]) => {
             const { parseMessage } = await import("./static/mesh.js");
             const r = await fetch(`/v1/sessions/${sid}/mesh?format_version=2&frame=server`
               + "&max_bytes=67108864", { headers: { Authorization: `Bearer ${token}` } });
             const buffer = await r.arrayBuffer();
             const m = parseMessage(buffer);
             const refusals = [];
             for (const bad of [buffer.slice(0, 30), buffer.slice(0, buffer.byteLength - 1),
                                new Uint8Array(64).buffer]) {
               try { parseMessage(bad); refusals.push(null); }
               catch (e) { refusals.push(e.message); }
             }
             return { version: m.version, generation: m.generation, boneVersion: m.boneVersion,
                      chunks: m.chunks.length,
                      vertices: m.chunks.reduce((a, c) => a + c.positions.length / 3, 0),
                      triangles: m.chunks.reduce((a, c) => a + c.triangles.length / 3, 0),
                      first: Array.from(m.chunks[0].positions.slice(0, 3)),
                      labels: [...new Set(m.chunks.flatMap((c) => Array.from(c.labels)))],
                      refusals };
           }""", [TOKEN, SID])
    assert got["version"] == 2 and got["generation"] == expected.generation
    assert got["chunks"] == len(expected.chunks)
    assert got["vertices"] == sum(len(c.positions) for c in expected.chunks)
    assert got["triangles"] == sum(len(c.triangles) for c in expected.chunks)
    assert got["first"] == pytest.approx(expected.chunks[0].positions[0].tolist())
    assert got["labels"] == [1]  # cortical only
    assert "truncated" in got["refusals"][0] and "truncated" in got["refusals"][1]
    assert "not a BFMC" in got["refusals"][2]
    offline.check()
