"""The dashboard in a real browser (Debian's Chromium driven by Playwright): `leco serve` on the
embedded default, a smoke job followed on the page to succeeded with curves, the render and the
occupancy picture, and a second job cancelled from the page. Screenshots go to
test-artifacts/dashboard/."""

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.helpers import ROOT, free_port

pytestmark = pytest.mark.slow
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
SHOTS = ROOT / "test-artifacts" / "dashboard"


@pytest.fixture
def service(tmp_path):
    if not Path(CHROMIUM).exists():
        pytest.skip(
            "Debian's chromium is not installed (.ci/run installs it: apt-get install chromium)"
        )
    pytest.importorskip(
        "playwright.sync_api", reason="playwright is a dev dependency (pip install -e '.[dev]')"
    )
    port = free_port()
    env = {**os.environ, "LECO_DATA_DIR": str(tmp_path / "data"), "LECO_LOCAL_CPUS": "2"}
    for key in ("DATABASE_URL", "LECO_API_TOKENS", "RAY_ADDRESS", "LECO_RAY_JOBS_ADDRESS"):
        env.pop(key, None)
    log = open(tmp_path / "serve.log", "w")
    server = subprocess.Popen(
        [sys.executable, "-m", "cli", "serve", "--port", str(port)],
        cwd=ROOT,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert server.poll() is None, (tmp_path / "serve.log").read_text()
            time.sleep(0.5)
        token = (tmp_path / "data" / "api-token").read_text().strip()
        yield (
            url,
            httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=30),
            token,
        )
    finally:
        os.killpg(server.pid, 15)
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, 9)
        log.close()


def test_the_dashboard_follows_a_job_and_cancels_another(service):
    from playwright.sync_api import expect, sync_playwright

    url, api, token = service
    scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
    while scene["state"] == "generating":
        time.sleep(0.3)
        scene = api.get(f"/v1/scenes/{scene['id']}").json()
    first = api.post(
        "/v1/jobs",
        json={
            "scene": scene["id"],
            "method": "leco",
            "profile": "smoke",
            "workers": 2,
            "metrics_every": 2,
            "val_every": 20,
        },
    ).json()
    SHOTS.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1280, "height": 1600})
        # the Content-Security-Policy must not block anything the dashboard itself does
        blocked = []
        page.on(
            "console",
            lambda m: blocked.append(m.text) if "Content Security Policy" in m.text else None,
        )
        page.goto(f"{url}/")
        expect(page.locator("#token-dialog")).to_be_visible()  # the page asks for the token once
        page.fill("#token-input", token)
        page.click("#token-form button")
        expect(page.locator(f'tr[data-job="{first["id"]}"]')).to_be_visible()
        page.screenshot(path=SHOTS / "jobs.png")
        page.click(f'tr[data-job="{first["id"]}"]')
        expect(page.locator("#job-state [data-state]")).to_have_attribute(
            "data-state", "succeeded", timeout=240_000
        )
        expect(page.locator("#occupancy-top")).not_to_have_attribute(
            "data-points", "0", timeout=30_000
        )
        points = page.eval_on_selector_all(
            "#charts svg.chart", "els => els.map(e => Number(e.dataset.points))"
        )
        assert points[0] >= 20 and points[1] >= 20  # loss and PSNR of both phases, every 2 steps
        assert page.eval_on_selector("#render", "img => img.complete && img.naturalWidth") > 0
        assert int(page.get_attribute("#occupancy-top", "data-points")) > 0
        assert "to the empty expert" in page.inner_text("#occupancy-stats")
        assert page.locator("#artifacts tbody tr").count() >= 8
        page.screenshot(path=SHOTS / "job-succeeded.png", full_page=True)
        # kept for the session: no second prompt on reload
        assert sessionStorage_token(page) == token
        page.reload()
        expect(page.locator("#job-state [data-state]")).to_have_attribute("data-state", "succeeded")
        assert not page.locator("#token-dialog").is_visible()

        second = api.post(
            "/v1/jobs",
            json={
                "scene": scene["id"],
                "method": "switch",
                "profile": "smoke",
                "overrides": {"main_steps": 20000},
            },
        ).json()
        page.goto(f"{url}/dashboard/#/jobs/{second['id']}")
        expect(page.locator("#job-state [data-state]")).to_have_attribute(
            "data-state", "running", timeout=60_000
        )
        deadline = time.monotonic() + 60
        while (
            api.get(f"/v1/jobs/{second['id']}").json()["step"] < 50 and time.monotonic() < deadline
        ):
            time.sleep(0.3)  # some metrics first, for the comparison view below
        page.click("#cancel")
        expect(page.locator("#job-state [data-state]")).to_have_attribute(
            "data-state", "cancelled", timeout=60_000
        )
        page.screenshot(path=SHOTS / "job-cancelled.png", full_page=True)

        page.goto(f"{url}/dashboard/#/scenes")
        page.click(f'tr[data-scene="{scene["id"]}"] a')
        expect(page.locator("#scene-map g.camera")).to_have_count(scene["cameras"])
        expect(page.locator("#bounds")).to_have_count(1)
        page.screenshot(path=SHOTS / "scene.png", full_page=True)
        page.goto(f"{url}/dashboard/#/compare/{scene['id']}")
        expect(page.locator("#compare tbody tr")).to_have_count(2)
        assert int(page.get_attribute("#compare-chart svg.chart", "data-points")) >= 10
        # one point per job
        for chart in ("#pareto-samples svg.scatter", "#pareto-speed svg.scatter"):
            assert int(page.get_attribute(chart, "data-points")) == 2
        switch_row = page.locator(f'#compare tr[data-job="{second["id"]}"] td.speedup').inner_text()
        # LeCO's speed-up at equal PSNR
        assert switch_row.endswith("x") and float(switch_row[:-1]) > 0
        page.screenshot(path=SHOTS / "compare.png", full_page=True)
        assert blocked == [], blocked
        browser.close()
    job = api.get(f"/v1/jobs/{second['id']}").json()
    assert job["state"] == "cancelled" and job["step"] < 20000


def sessionStorage_token(page) -> str:
    return page.evaluate("() => sessionStorage.getItem('leco-token')")


def test_the_dashboard_renders_videos_and_views_a_finished_job(service):
    """On the page: a render submitted from the job view's form plays in a <video> (H.264 through a
    blob: URL, under the Content-Security-Policy), a bad one shows the API's 422; the viewer answers
    a drag with low-resolution frames and a sharp one once the pointer rests; two of its cameras
    render as a path."""
    from playwright.sync_api import expect, sync_playwright

    url, api, token = service
    scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
    while scene["state"] == "generating":
        time.sleep(0.3)
        scene = api.get(f"/v1/scenes/{scene['id']}").json()
    job = api.post(
        "/v1/jobs", json={"scene": scene["id"], "method": "leco", "profile": "smoke", "workers": 1}
    ).json()
    SHOTS.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1280, "height": 1400})
        blocked = []
        page.on(
            "console",
            lambda m: blocked.append(m.text) if "Content Security Policy" in m.text else None,
        )
        page.goto(f"{url}/dashboard/#/jobs/{job['id']}")
        page.fill("#token-input", token)
        page.click("#token-form button")
        h264 = page.evaluate(
            "() => document.createElement('video').canPlayType('video/mp4; codecs=\"avc1.640015\"')"
        )
        assert h264 in ("probably", "maybe"), f"this Chromium cannot play H.264 ({h264!r})"
        # the cards appear once the training job the page follows has succeeded
        expect(page.locator("#render-form")).to_be_visible(timeout=300_000)
        expect(page.locator("#job-state [data-state]")).to_have_attribute("data-state", "succeeded")

        # a video over the API's pixel budget: the 422 names the field
        form = page.locator("#render-form")
        form.locator("input[name=frames]").fill("1200")
        form.locator("select[name=size]").select_option("640x480")
        form.locator("button[type=submit]").click()
        expect(page.locator("#render-error")).to_contain_text("frames: ")
        expect(page.locator("#render-error")).to_contain_text("more than 60,000,000")
        form.locator("select[name=kind]").select_option("orbit")
        form.locator("input[name=frames]").fill("8")
        form.locator("select[name=size]").select_option("160x120")
        form.locator("button[type=submit]").click()
        expect(page.locator("#render-error")).to_be_empty()
        orbit = page.locator("#render-list .render-item").first
        expect(orbit.locator(".render-state [data-state]")).to_have_attribute(
            "data-state", "succeeded", timeout=180_000
        )
        video = orbit.locator("video.render-video")
        expect(video).to_be_visible(timeout=30_000)
        video.evaluate(
            "v => new Promise((ok, no) => { const t = setTimeout(() => no(new Error('no data')), "
            "20000); const check = () => v.readyState >= 2 ? (clearTimeout(t), ok()) : "
            "setTimeout(check, 50); check(); })"
        )
        assert video.evaluate("v => [v.videoWidth, v.videoHeight]") == [160, 120]
        assert video.evaluate("v => v.src.startsWith('blob:') && v.poster.startsWith('blob:')")
        video.evaluate("v => v.play()")
        page.wait_for_function(
            "v => !v.paused && v.currentTime > 0.05", arg=video.element_handle(), timeout=10_000
        )
        # decoded, not just timed
        assert video.evaluate("v => v.getVideoPlaybackQuality().totalVideoFrames") >= 2
        # the video, its poster, camera path and summary
        assert orbit.locator(".links a.dl").count() >= 4
        page.locator("#renders-card").screenshot(path=SHOTS / "renders.png")

        image = page.locator("#viewer-image")
        # the first view, sharp
        expect(image).to_have_attribute("data-size", "320x240", timeout=120_000)

        def drag_until_a_frame(dx):
            """Holds the button down and keeps moving until a new frame arrives: a low-resolution
            one."""
            frames, box = int(image.get_attribute("data-frames")), image.bounding_box()
            x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            page.mouse.move(x, y)
            page.mouse.down()
            deadline = time.monotonic() + 60
            while int(image.get_attribute("data-frames")) == frames:
                assert time.monotonic() < deadline, "no frame arrived while dragging"
                x, y = x + dx, y + 1
                page.mouse.move(x, y, steps=2)
                page.wait_for_timeout(100)
            assert image.get_attribute("data-size") == "80x60"
            frames = int(image.get_attribute("data-frames"))
            page.mouse.up()  # at rest: a sharp frame of where the drag ended
            page.wait_for_function(
                "([img, n]) => Number(img.dataset.frames) > n && img.dataset.size === '320x240'",
                arg=[image.element_handle(), frames],
                timeout=60_000,
            )

        drag_until_a_frame(6)
        page.click("#add-camera")
        expect(page.locator("#path-cameras li")).to_have_count(1)
        expect(page.locator("#render-path")).to_be_disabled()
        frames, box = int(image.get_attribute("data-frames")), image.bounding_box()
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.mouse.wheel(0, -200)  # zoom in a little: a sharp frame once the wheel rests
        page.wait_for_function(
            "([img, n]) => Number(img.dataset.frames) > n && img.dataset.size === '320x240'",
            arg=[image.element_handle(), frames],
            timeout=60_000,
        )
        page.wait_for_timeout(500)  # nothing more on its way
        drag_until_a_frame(-8)
        page.click("#add-camera")
        expect(page.locator("#path-cameras li")).to_have_count(2)
        page.screenshot(path=SHOTS / "viewer-full.png", full_page=True)
        page.locator("#viewer").screenshot(path=SHOTS / "viewer.png")
        page.click("#render-path")
        expect(page.locator("#render-list .render-item")).to_have_count(2)
        path_item = page.locator("#render-list .render-item").first
        expect(path_item.locator(".render-state [data-state]")).to_have_attribute(
            "data-state", "succeeded", timeout=180_000
        )
        expect(path_item.locator("video.render-video")).to_be_visible(timeout=30_000)
        renders = api.get(f"/v1/jobs/{job['id']}/renders").json()["items"]
        assert [r["state"] for r in renders] == ["succeeded", "succeeded"]
        path = renders[0]["config"]["path"]
        assert path["kind"] == "cameras" and path["frame"] == "world" and path["interpolate"]
        assert len(path["cameras"]) == 2 and path["cameras"][0]["c2w"] != path["cameras"][1]["c2w"]
        assert renders[0]["config"]["frames"] == 8 and renders[0]["config"]["width"] == 160
        page.locator("#work-area").screenshot(path=SHOTS / "renders-path.png")

        page.goto(f"{url}/dashboard/#/")  # the jobs list shows training jobs only
        expect(page.locator("tr.job-row")).to_have_count(1)
        assert blocked == [], blocked
        browser.close()
