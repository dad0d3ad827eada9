"""The pages in a real browser: Debian's Chromium (headless, driven by Selenium through
chromium-driver) against a real ``bssrdf serve`` and a real ``bssrdf worker``.

A small sweep is submitted with a description holding markup; its job page, opened while the job
is still queued, follows it to done without a reload; the dataset version's figures render (SVG
images loaded, with a size) without console errors; an export link followed by the browser gives
the bytes whose sha256 the server records; the description shows as text; a signed-in user
cancels a job with the page's button. Skipped with the reason where Chromium, its driver or
Selenium is missing (.ci/run installs them).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.support.browser import browser_problem, chromium, console_errors
from tests.support.net import free_port
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.skipif(browser_problem() is not None, reason=str(browser_problem()))]

REPO = Path(__file__).resolve().parents[2]
TOKEN = "browser-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
DESCRIPTION = 'Two albedos <script>window.__xss = 1</script><img src=x onerror="window.__xss = 2"> & more'
SWEEP = {
    "name": "browser-sweep", "description": DESCRIPTION,
    "sweep": {"albedo": [0.8, 0.95], "g": [0.5], "eta": [1.3]},
    "incidence_deg": [0], "photons": 400, "shards": 2, "seed": 3, "estimator": "exits",
    "bins": {"radial": {"count": 8, "max_mfp": 8}, "cos_theta_o": {"count": 2}, "phi_o": {"count": 4}},
}


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture
def service(tmp_path):
    """(base URL, start_worker) of a running ``bssrdf serve`` with one token and open reads."""
    port = free_port()
    db, storage = f"sqlite:///{tmp_path / 'jobs.sqlite'}", str(tmp_path / "data")
    env = {**os.environ, "PYTHONPATH": str(REPO), "BSSRDF_COMPILE": "0", "OMP_NUM_THREADS": "1",
           "BSSRDF_API_TOKENS": json.dumps([TOKEN]), "BSSRDF_DATA_DIR": str(tmp_path / "unused")}
    log = open(tmp_path / "serve.log", "wb")
    procs = [subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--host", "127.0.0.1", "--port", str(port), "--db", db,
         "--storage", storage, "--log-level", "warning"],
        cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)]
    base = f"http://127.0.0.1:{port}"

    def up():
        if procs[0].poll() is not None:
            raise AssertionError(f"bssrdf serve exited: {(tmp_path / 'serve.log').read_text()}")
        try:
            return httpx.get(f"{base}/readyz", timeout=2).status_code == 200
        except httpx.TransportError:
            return False

    def start_worker(**extra_env: str) -> subprocess.Popen:
        with open(tmp_path / "worker.log", "ab") as out:
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "service.cli", "worker", "--db", db, "--storage", storage, "--poll-seconds",
                 "0.1", "--max-poll-seconds", "0.5", "--lease-seconds", "30"],
                cwd=tmp_path, env={**env, **extra_env}, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL))
        return procs[-1]

    try:
        wait_for(up, 30, "bssrdf serve to be ready", poll=0.2)
        yield base, start_worker
    finally:
        for proc in reversed(procs):
            _stop(proc)
        log.close()


def _live_state(driver) -> tuple[str, str]:
    return tuple(driver.execute_script(
        "var s = document.getElementById('live'); return [s.dataset.live, s.querySelector('.state').textContent];"))


def _stopped(proc: subprocess.Popen) -> bool:
    """Whether proc has stopped (SIGSTOP); AssertionError if it exited instead."""
    pid, status = os.waitpid(proc.pid, os.WUNTRACED | os.WNOHANG)
    if pid == 0:
        return False
    assert os.WIFSTOPPED(status), f"the worker exited (status {status}) instead of stopping"
    return True


def test_a_sweep_from_submission_to_its_figures_and_exports(service):
    base, start_worker = service
    job = httpx.post(f"{base}/v1/jobs", json={"spec": SWEEP}, headers=AUTH, timeout=30).json()
    with chromium() as driver:
        driver.get(f"{base}/jobs/{job['id']}")
        assert _live_state(driver) == ("true", "queued")
        assert "waiting for a worker" in driver.find_element("id", "status").text
        driver.execute_script("window.__sameDocument = 'yes';")  # gone if the page reloads
        # The walk of 400 photons takes less than the page's poll, so the worker stops itself with
        # the tables staged (service/faults.py) until the page has shown the job under way.
        worker = start_worker(BSSRDF_TEST_PAUSE_AT="staged")
        # The page shows "merging" from the merge task's claim on, before the worker reaches the
        # staged tables and stops: continue it only once it has stopped (a SIGCONT sent before the
        # stop is lost and leaves the worker stopped for good).
        wait_for(lambda: _stopped(worker), 240, "the worker to stop with the tables staged", poll=0.05)
        wait_for(lambda: _live_state(driver)[1] == "merging", 240, "the job page to show the merge under way",
                 poll=0.25)
        os.kill(worker.pid, signal.SIGCONT)
        states = set()

        def ended():
            live, state = _live_state(driver)
            states.add(state)
            return live == "false" and state

        assert wait_for(ended, 240, "the job page to show the job ended", poll=0.25) == "succeeded"
        assert driver.execute_script("return window.__sameDocument") == "yes"  # updated in place
        assert driver.find_element("id", "shards").text == "2 / 2"  # both albedos share one walk of 2 shards
        assert console_errors(driver) == []

        # the description is text on the job page
        description = driver.find_element("css selector", "p.description")
        assert description.text == DESCRIPTION
        assert driver.execute_script("return window.__xss") is None
        assert all(s.get_attribute("src").startswith(f"{base}/static/") for s in
                   driver.find_elements("css selector", "script"))

        # the dataset version: figures rendered, no console errors
        driver.find_element("css selector", "#result a").click()
        wait_for(lambda: driver.find_elements("id", "figures"), 60, "the version page")
        assert driver.find_element("id", "description").text == DESCRIPTION
        images = driver.find_elements("css selector", "#figures img")
        kinds = {img.get_attribute("src").rsplit("/", 1)[1].split("-")[0] for img in images}
        assert {"rd", "s", "albedo"} <= kinds, kinds  # Rd(r), S, the albedo map of the sweep
        for img in images:
            driver.execute_script("arguments[0].scrollIntoView();", img)
            wait_for(lambda: driver.execute_script("return arguments[0].complete && arguments[0].naturalWidth > 0",
                                                   img), 30, f"figure {img.get_attribute('src')} to load")
            assert img.size["width"] > 300 and img.size["height"] > 100, img.get_attribute("src")
            kind = driver.execute_script(
                "return fetch(arguments[0]).then(r => r.headers.get('content-type'))", img.get_attribute("src"))
            assert kind == "image/svg+xml"
        assert console_errors(driver) == []
        assert driver.execute_script("return window.__xss") is None

        # follow an export link in the browser and hash what it receives
        link = driver.find_element("css selector", "a.export-link[data-format='csv']")
        href = link.get_attribute("href")
        digest, etag = driver.execute_script("""
            return fetch(arguments[0]).then(r => r.arrayBuffer().then(b => crypto.subtle.digest('SHA-256', b))
              .then(d => [Array.from(new Uint8Array(d)).map(x => x.toString(16).padStart(2, '0')).join(''),
                          r.headers.get('etag')]));""", href)
        assert etag == f'"{digest}"'
        driver.refresh()
        shown = driver.find_element("css selector", "a.export-link[data-format='csv']").find_element(
            "xpath", "../../td[3]/code").get_attribute("title")
        assert shown == digest  # the page now lists the export with the sha256 the browser computed
        table = driver.find_element("css selector", "#downloads a[href$='/files/summary.json']").get_attribute("href")
        assert httpx.get(table).status_code == 200
        assert console_errors(driver) == []


def test_a_signed_in_user_cancels_a_job_with_the_button(service):
    base, _ = service
    spec = dict(SWEEP, name="to-cancel", seed=4)
    job = httpx.post(f"{base}/v1/jobs", json={"spec": spec}, headers=AUTH, timeout=30).json()
    with chromium() as driver:
        driver.get(f"{base}/jobs/{job['id']}")
        assert not driver.find_elements("css selector", f"form[action='/jobs/{job['id']}/cancel']")
        driver.find_element("css selector", "#live a[href^='/signin']").click()
        driver.find_element("id", "token").send_keys(TOKEN)
        driver.find_element("css selector", "form.signin button").click()
        wait_for(lambda: driver.current_url == f"{base}/jobs/{job['id']}", 30, "the redirect back to the job")
        assert driver.get_cookie("bssrdf_session")["httpOnly"] is True
        driver.find_element("css selector", f"form[action='/jobs/{job['id']}/cancel'] button").click()
        wait_for(lambda: _live_state(driver) == ("false", "cancelled"), 30, "the job page to show it cancelled")
        assert httpx.get(f"{base}/v1/jobs/{job['id']}").json()["state"] == "cancelled"
        assert console_errors(driver) == []
