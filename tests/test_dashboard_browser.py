"""The dashboard in a real browser (Debian's Chromium driven by Playwright): `leco serve` on the embedded
default, a smoke job followed on the page to succeeded with curves, the render and the occupancy picture,
and a second job cancelled from the page. Screenshots go to test-artifacts/dashboard/."""

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.conftest import free_port

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
SHOTS = ROOT / "test-artifacts" / "dashboard"


@pytest.fixture
def service(tmp_path):
    if not Path(CHROMIUM).exists():
        pytest.skip("Debian's chromium is not installed (.ci/run installs it: apt-get install chromium)")
    pytest.importorskip("playwright.sync_api", reason="playwright is a dev dependency (pip install -e '.[dev]')")
    port = free_port()
    env = {**os.environ, "LECO_DATA_DIR": str(tmp_path / "data"), "LECO_LOCAL_CPUS": "2"}
    for key in ("DATABASE_URL", "LECO_API_TOKENS", "RAY_ADDRESS", "LECO_RAY_JOBS_ADDRESS"):
        env.pop(key, None)
    log = open(tmp_path / "serve.log", "w")
    server = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port)], cwd=ROOT, env=env,
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
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
        yield url, httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=30), token
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
    first = api.post("/v1/jobs", json={"scene": scene["id"], "method": "leco", "profile": "smoke", "workers": 2,
                                       "metrics_every": 2, "val_every": 20}).json()
    SHOTS.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1280, "height": 1600})
        blocked = []  # the Content-Security-Policy must not block anything the dashboard itself does
        page.on("console", lambda m: blocked.append(m.text) if "Content Security Policy" in m.text else None)
        page.goto(f"{url}/")
        expect(page.locator("#token-dialog")).to_be_visible()  # the page asks for the token once
        page.fill("#token-input", token)
        page.click("#token-form button")
        expect(page.locator(f'tr[data-job="{first["id"]}"]')).to_be_visible()
        page.screenshot(path=SHOTS / "jobs.png")
        page.click(f'tr[data-job="{first["id"]}"]')
        expect(page.locator("#job-state [data-state]")).to_have_attribute("data-state", "succeeded", timeout=240_000)
        expect(page.locator("#occupancy-top")).not_to_have_attribute("data-points", "0", timeout=30_000)
        points = page.eval_on_selector_all("#charts svg.chart", "els => els.map(e => Number(e.dataset.points))")
        assert points[0] >= 20 and points[1] >= 20  # loss and PSNR of both phases, every 2 steps
        assert page.eval_on_selector("#render", "img => img.complete && img.naturalWidth") > 0
        assert int(page.get_attribute("#occupancy-top", "data-points")) > 0
        assert "to the empty expert" in page.inner_text("#occupancy-stats")
        assert page.locator("#artifacts tbody tr").count() >= 8
        page.screenshot(path=SHOTS / "job-succeeded.png", full_page=True)
        assert sessionStorage_token(page) == token  # kept for the session: no second prompt on reload
        page.reload()
        expect(page.locator("#job-state [data-state]")).to_have_attribute("data-state", "succeeded")
        assert not page.locator("#token-dialog").is_visible()

        second = api.post("/v1/jobs", json={"scene": scene["id"], "method": "switch", "profile": "smoke",
                                            "overrides": {"main_steps": 20000}}).json()
        page.goto(f"{url}/dashboard/#/jobs/{second['id']}")
        expect(page.locator("#job-state [data-state]")).to_have_attribute("data-state", "running", timeout=60_000)
        deadline = time.monotonic() + 60
        while api.get(f"/v1/jobs/{second['id']}").json()["step"] < 50 and time.monotonic() < deadline:
            time.sleep(0.3)  # some metrics first, for the comparison view below
        page.click("#cancel")
        expect(page.locator("#job-state [data-state]")).to_have_attribute("data-state", "cancelled", timeout=60_000)
        page.screenshot(path=SHOTS / "job-cancelled.png", full_page=True)

        page.goto(f"{url}/dashboard/#/scenes")
        page.click(f'tr[data-scene="{scene["id"]}"] a')
        expect(page.locator("#scene-map g.camera")).to_have_count(scene["cameras"])
        expect(page.locator("#bounds")).to_have_count(1)
        page.screenshot(path=SHOTS / "scene.png", full_page=True)
        page.goto(f"{url}/dashboard/#/compare/{scene['id']}")
        expect(page.locator("#compare tbody tr")).to_have_count(2)
        assert int(page.get_attribute("#compare-chart svg.chart", "data-points")) >= 10
        for chart in ("#pareto-samples svg.scatter", "#pareto-speed svg.scatter"):  # one point per job
            assert int(page.get_attribute(chart, "data-points")) == 2
        switch_row = page.locator(f'#compare tr[data-job="{second["id"]}"] td.speedup').inner_text()
        assert switch_row.endswith("x") and float(switch_row[:-1]) > 0  # LeCO's speed-up at equal PSNR
        page.screenshot(path=SHOTS / "compare.png", full_page=True)
        assert blocked == [], blocked
        browser.close()
    job = api.get(f"/v1/jobs/{second['id']}").json()
    assert job["state"] == "cancelled" and job["step"] < 20000


def sessionStorage_token(page) -> str:
    return page.evaluate("() => sessionStorage.getItem('leco-token')")
