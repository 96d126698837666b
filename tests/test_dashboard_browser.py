"""The dashboard in a real browser: headless Chromium driven by Selenium against a real
``hktex serve`` child process with two owners' tokens and a worker.

What a person would do: sign in (a wrong token first), upload a mesh with its texture and start
a tiny UV fit, watch its progress move, open the 3D viewer and switch it to the error map,
cancel a long job; and check that another owner's mesh never shows and that /docs and /redoc
render from the package alone. Every page is saved as a screenshot under the test's tmp dir
and checked not to be blank (a page that renders nothing is a failure even if its HTML is
right). Skips when chromium, chromedriver or selenium are missing; ``scripts/setup.sh``
installs them, so CI runs it.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.server_support import free_port, kill_group

pytestmark = pytest.mark.browser

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
TOKENS = "tok-alice:alice,tok-bob:bob"
# the tiniest grid and fit that still make a kernel set (tests/test_demo.py uses the same)
SPECTRA = {"angles": "2", "anisotropies": "1,10", "k": "8", "k-iso": "6"}


def _require_browser():
    if not (CHROMIUM and CHROMEDRIVER):
        pytest.skip("chromium and chromedriver are not installed (scripts/setup.sh installs them)")
    try:
        import selenium  # noqa: F401
    except ImportError:
        pytest.skip("selenium is not installed (pip install -e '.[dev]')")


@pytest.fixture(scope="module")
def assets(tmp_path_factory) -> dict[str, Path]:
    from hktex_engine.evaluation.synthetic import textured_demo, write_textured_obj

    root = tmp_path_factory.mktemp("assets")
    v, f, uv, tex = textured_demo(subdivisions=2, texture_size=64)
    alice = write_textured_obj(root / "alice_blob.obj", v, f, uv, tex)
    bob = write_textured_obj(root / "bob_secret.obj", v * 1.5, f, uv, tex)
    return {
        "mesh": alice,
        "texture": alice.with_name("alice_blob_albedo.png"),
        "bob": bob,
        "bob_texture": bob.with_name("bob_secret_albedo.png"),
    }


@pytest.fixture(scope="module")
def service(tmp_path_factory, assets) -> str:
    _require_browser()
    from hktex_client import Client

    data = tmp_path_factory.mktemp("dashboard-data")
    env = {
        "HKTEX_DATA_DIR": str(data),
        "HKTEX_WORKERS": "1",
        "HKTEX_TOKENS": TOKENS,
        "HKTEX_POLL_SECONDS": "0.2",
        "HKTEX_HEARTBEAT_SECONDS": "0.5",
        "HKTEX_CANCEL_GRACE_SECONDS": "2",
        "HKTEX_JOB_THREADS": "1",
        "OMP_NUM_THREADS": "1",
    }
    with _serve(data, env) as url:
        with Client(url, token="tok-bob") as bob:  # another owner's object, never to be shown
            bob.upload_mesh(assets["bob"], texture=assets["bob_texture"])
        yield url


@contextlib.contextmanager
def _serve(data: Path, env: dict[str, str]):
    """The app under uvicorn in a child process (settings from ``HKTEX_*``): Dr.Jit renders
    and torch bakes then run outside the test's interpreter, as in production."""
    from hktex_client import Client

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "uvicorn", "--factory", "hktex_server.app:create_app"]
    cmd += ["--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"]
    with (data / "serve.log").open("ab") as log:
        proc = subprocess.Popen(
            cmd,
            stdout=log,
            stderr=subprocess.STDOUT,
            env={**os.environ, **env},
            start_new_session=True,
        )
        try:
            with Client(url, timeout=5, retries=0) as client:
                deadline = time.monotonic() + 120
                while True:
                    assert proc.poll() is None, f"the service exited; see {log.name}"
                    try:
                        client.health()
                        break
                    except Exception:
                        assert time.monotonic() < deadline, "the service did not start"
                        time.sleep(0.2)
            yield url
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                kill_group(proc.pid)
                proc.wait()


@pytest.fixture(scope="module")
def browser():
    _require_browser()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--window-size=1400,1800",
        # WebGL without a GPU: ANGLE on SwiftShader (Chromium needs the explicit opt-in)
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--ignore-gpu-blocklist",
    ):
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    driver.set_page_load_timeout(60)
    yield driver
    driver.quit()


def _wait(driver, what: str, pred, timeout: float = 60.0):
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(driver, timeout, poll_frequency=0.2).until(
        lambda d: pred(d), message=f"timed out waiting for {what}"
    )


def shot(driver, path: Path, element=None) -> Path:
    """Save a screenshot and fail if it (or the element's area) is one flat colour."""
    from PIL import Image

    driver.save_screenshot(str(path))
    img = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)
    assert img.std() > 8, f"{path.name} looks blank (std {img.std():.1f})"
    if element is not None:
        r = driver.execute_script(
            "const b = arguments[0].getBoundingClientRect();"
            "return [b.left * devicePixelRatio, b.top * devicePixelRatio,"
            " b.width * devicePixelRatio, b.height * devicePixelRatio];",
            element,
        )
        x, y, w, h = (int(v) for v in r)
        crop = img[max(y, 0) : y + h, max(x, 0) : x + w]
        assert crop.size and crop.std() > 8, f"{path.name}: the element renders blank"
    return path


def _sign_in(driver, url: str, token: str) -> None:
    from selenium.webdriver.common.by import By

    driver.get(url + "/")
    driver.execute_script("sessionStorage.clear()")
    driver.get(url + "/")
    box = _wait(driver, "the sign-in form", lambda d: d.find_element(By.ID, "token").is_displayed())
    assert box
    driver.find_element(By.ID, "token").send_keys(token)
    driver.find_element(By.ID, "login-btn").click()


def test_wrong_token_shows_a_clear_message(service, browser, tmp_path) -> None:
    from selenium.webdriver.common.by import By

    _sign_in(browser, service, "not-a-token")
    msg = _wait(browser, "the refusal", lambda d: d.find_element(By.ID, "login-msg").text)
    assert "refused this token" in msg and "invalid token" in msg
    assert not browser.find_element(By.ID, "app").is_displayed()
    # never in a URL, not kept after a refusal
    assert "not-a-token" not in browser.current_url
    assert browser.execute_script("return sessionStorage.getItem('hktex.token')") is None
    shot(browser, tmp_path / "wrong_token.png")


def test_api_docs_render_offline(service, browser, tmp_path) -> None:
    from selenium.webdriver.common.by import By

    for page, ready in (("/docs", ".swagger-ui .opblock"), ("/redoc", "[data-section-id]")):
        browser.get(service + page)
        _wait(browser, f"{page} to render", lambda d, r=ready: d.find_elements(By.CSS_SELECTOR, r))
        sources = browser.execute_script(
            "return performance.getEntriesByType('resource')"
            ".filter(e => e.initiatorType !== 'img').map(e => e.name)"
        )
        # scripts, styles and the spec all from the service; ReDoc's "powered by" footer
        # logo is an <img> from its CDN, missing offline without harm
        assert sources and all(s.startswith(service) for s in sources), sources
        assert "meshes" in browser.find_element(By.TAG_NAME, "body").text
        shot(browser, tmp_path / f"{page.strip('/')}.png")


def test_dashboard_upload_fit_progress_viewer_cancel(service, browser, assets, tmp_path) -> None:
    from selenium.webdriver.common.by import By

    _sign_in(browser, service, "tok-alice")
    _wait(browser, "the dashboard", lambda d: d.find_element(By.ID, "app").is_displayed())
    assert browser.find_element(By.ID, "owner").text == "alice"
    assert browser.execute_script("return sessionStorage.getItem('hktex.token')") == "tok-alice"
    assert "tok-alice" not in browser.current_url
    shot(browser, tmp_path / "1_signed_in.png")

    # upload + a fit long enough to be watched
    browser.find_element(By.ID, "mesh-file").send_keys(str(assets["mesh"]))
    browser.find_element(By.ID, "texture-file").send_keys(str(assets["texture"]))
    browser.find_element(By.CSS_SELECTOR, "#upload-card details summary").click()
    fields = {"kernels": "32", "max-kernels": "64", "steps": "600", **SPECTRA}
    for name, value in fields.items():
        browser.find_element(By.ID, name).send_keys(value)
    browser.find_element(By.ID, "upload-btn").click()
    _wait(browser, "the upload", lambda d: "queued" in d.find_element(By.ID, "upload-msg").text)
    row = "#jobs tr[data-job-id]"
    steps_seen: set[int] = set()

    def newest_job(d) -> dict | None:
        # read in one script: the table is re-rendered under Selenium's feet
        return d.execute_script(
            "const r = document.querySelector(arguments[0]);"
            "return r && {id: r.dataset.jobId, state: r.dataset.state, step: +r.dataset.step,"
            " cancel: !!r.querySelector('button.cancel')}",
            row,
        )

    def progressed(d) -> bool:
        job = newest_job(d)
        if job is None:
            return False
        steps_seen.add(job["step"])
        return job["state"] == "succeeded"

    _wait(browser, "the fit to finish", progressed, timeout=240)
    assert len([s for s in steps_seen if s > 0]) >= 2, f"progress never moved: {steps_seen}"
    assert browser.find_elements(By.CSS_SELECTOR, "#jobs svg.spark path"), "no loss curve"
    shot(browser, tmp_path / "2_fit_done.png")

    # another owner's objects never appear
    page = browser.find_element(By.TAG_NAME, "body").text
    assert "alice_blob.obj" in page and "bob_secret" not in page

    # the viewer: baked GLB, then the error map on the same mesh
    _wait(
        browser,
        "the kernel set",
        lambda d: d.find_elements(By.CSS_SELECTOR, "#kernelsets button.view"),
    )
    browser.find_element(By.CSS_SELECTOR, "#kernelsets button.view").click()
    mv = browser.find_element(By.ID, "mv")
    _wait(browser, "the GLB", lambda d: mv.get_attribute("data-layer") == "kernel", timeout=180)
    _wait(browser, "a rendered frame", lambda d: d.execute_script("return arguments[0].loaded", mv))
    time.sleep(1.0)  # model-viewer fades the model in
    shot(browser, tmp_path / "3_viewer_kernel.png", element=mv)
    browser.find_element(By.ID, "layer-error").click()
    _wait(browser, "the error map", lambda d: mv.get_attribute("data-layer") == "error")
    time.sleep(0.5)
    assert browser.find_element(By.ID, "legend").is_displayed()
    shot(browser, tmp_path / "4_viewer_error.png", element=mv)
    browser.find_element(By.ID, "layer-original").click()
    _wait(browser, "the original texture", lambda d: mv.get_attribute("data-layer") == "original")
    _wait(
        browser,
        "the pictures",
        lambda d: (
            d.execute_script("return document.getElementById('pic-error').naturalWidth") >= 512
        ),
    )
    pictures = browser.find_element(By.ID, "pictures")
    # the curve is the record's (every step), not the few points this tab happened to see
    curve = browser.find_element(By.ID, "pic-curve")
    _wait(browser, "the loss curve", lambda d: curve.get_attribute("data-source") == "record")
    assert curve.find_elements(By.CSS_SELECTOR, "path") and "step 600" in curve.text
    browser.execute_script("arguments[0].scrollIntoView()", pictures)
    shot(browser, tmp_path / "5_pictures.png", element=pictures)

    # a long job, cancelled from the page
    browser.execute_script("window.scrollTo(0, 0)")
    browser.find_element(By.ID, "steps").clear()
    browser.find_element(By.ID, "steps").send_keys("100000")
    old = newest_job(browser)["id"]
    browser.find_element(By.CSS_SELECTOR, "#meshes tr[data-mesh-id] button").click()

    def running(d) -> bool:  # the new job, running and past its first steps: a real cancel
        job = newest_job(d) or {}
        return job.get("id") != old and job.get("state") == "running" and job.get("step", 0) > 0

    _wait(browser, "the long job to run", running, timeout=180)
    job_id = newest_job(browser)["id"]
    sel = f'#jobs tr[data-job-id="{job_id}"]'
    browser.execute_script(f"document.querySelector('{sel} button.cancel').click()")
    _wait(
        browser,
        "the cancellation",
        lambda d: (
            d.execute_script(f"return document.querySelector('{sel}').dataset.state") == "cancelled"
        ),
        timeout=120,
    )
    assert browser.find_elements(By.CSS_SELECTOR, f"{sel} button.retry")
    assert newest_job(browser)["step"] > 0, "it was cancelled while running, not while queued"
    browser.execute_script(f"document.querySelector('{sel}').scrollIntoView()")
    shot(browser, tmp_path / "6_cancelled.png")


def test_without_tokens_the_page_signs_in_as_local(browser, tmp_path) -> None:
    """The demo's and a fresh ``hktex serve``'s case: loopback, no tokens, no sign-in form."""
    from selenium.webdriver.common.by import By

    data = tmp_path / "data"
    data.mkdir()
    env = {"HKTEX_DATA_DIR": str(data), "HKTEX_WORKERS": "0", "HKTEX_TOKENS": ""}
    with _serve(data, env) as url:
        browser.get(url + "/")
        browser.execute_script("sessionStorage.clear()")
        browser.get(url + "/")
        _wait(browser, "the dashboard", lambda d: d.find_element(By.ID, "app").is_displayed())
        assert browser.find_element(By.ID, "owner").text == "local"
        assert not browser.find_element(By.ID, "login").is_displayed()
        shot(browser, tmp_path / "local.png")
