"""The web console in headless Debian Chromium (/usr/bin/chromium, never a downloaded browser):
it loads, shows live data fed over Zenoh, and its forms change the configuration."""

from __future__ import annotations

import re
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from shared.bus import Bus
from shared.messages import SafetyMode
from tests.test_config_api import (  # noqa: F401 (fixtures)
    TOKEN,
    ApiServer,
    FakeSafety,
    bus,
    human_state,
    wait_until,
    zenoh_endpoint,
)

pytestmark = pytest.mark.integration

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--no-first-run", "--disable-quic",
]
#: The browser logs the API's deliberate refusals (no token, invalid value) as failed loads: expected.
REFUSAL = re.compile(r"status of (401|422) ")
if not CHROMIUM.exists():
    pytest.skip("Debian chromium is not installed (.ci/run installs it: apt-get install chromium)", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api")


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory, zenoh_endpoint: str, bus: Bus) -> Iterator[ApiServer]:  # noqa: F811
    with ApiServer(tmp_path_factory.mktemp("console") / "config.json", zenoh_endpoint) as server:
        yield server


@pytest.fixture(scope="module")
def browser_context(tmp_path_factory: pytest.TempPathFactory) -> Iterator:
    with sync_api.sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            user_data_dir=str(tmp_path_factory.mktemp("chromium-profile")),  # fresh profile
            executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_FLAGS,
        )
        yield context
        context.close()


@pytest.fixture
def page(browser_context, console: ApiServer) -> Iterator:
    page = browser_context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda msg: errors.append(msg.text) if msg.type == "error" and not REFUSAL.search(msg.text) else None)
    page.goto(console.url + "/")
    sync_api.expect(page.locator("#config-version")).to_have_text("v" + str(console.http.get("/api/config").json()["version"]))
    yield page
    page.close()
    assert not errors, errors


def test_console_loads_with_the_current_parameters(page, browser_context, console: ApiServer) -> None:
    assert page.title() == "safemimic console"
    debian = subprocess.run([str(CHROMIUM), "--version"], capture_output=True, text=True, check=True).stdout
    version = re.search(r"Chromium (\d+\.\d+\.\d+\.\d+)", debian).group(1)
    product = browser_context.new_cdp_session(page).send("Browser.getVersion")["product"]
    assert product.endswith("/" + version), (product, version)  # the Debian browser, not a download
    safety = console.http.get("/api/config").json()["safety"]
    sync_api.expect(page.locator("#robot-id")).to_have_text("g1")
    assert float(page.locator("#safety-form input[name=gamma]").input_value()) == safety["gamma"]
    assert float(page.locator("#safety-form input[name=dt]").input_value()) == pytest.approx(safety["dt"])
    assert float(page.locator("#safety-form input[name=self_margin]").input_value()) == safety["self_margin"]
    assert page.locator("#safety-vectors input").count() == 4 * 8  # w, u_min, u_max, accel_max
    accel = [float(page.locator(f"#safety-form input[name='accel_max.{i}']").input_value()) for i in range(8)]
    assert accel == safety["accel_max"]
    assert page.locator("#pair-groups input:checked").count() == len(safety["enabled_pair_groups"])
    method = console.http.get("/api/config").json()["retarget"]["method"]
    assert page.locator("#retarget-form select[name=method]").input_value() == method


def test_console_shows_live_data(page, bus: Bus) -> None:  # noqa: F811
    with FakeSafety(bus, mode=SafetyMode.ACTIVE, h_self=0.031, h_human=0.142, ack=False):
        sync_api.expect(page.locator("#stream-state")).to_have_text("live")
        sync_api.expect(page.locator("#mode")).to_have_text("active")
        sync_api.expect(page.locator("#h-self")).to_have_text("0.031")
        sync_api.expect(page.locator("#h-human")).to_have_text("0.142")
        sync_api.expect(page.locator("#active")).to_have_text("3 / 63")
        wait_until(lambda: int(page.locator("#plot-h").get_attribute("data-samples")) >= 5)
    drawn = page.evaluate(
        """() => { const c = document.getElementById('plot-h');
                   const px = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                   let n = 0; for (let i = 3; i < px.length; i += 4) if (px[i] > 0) n++; return n; }"""
    )
    assert drawn > 200, "the h_min plot drew nothing"


def test_changing_gamma_in_the_form_reaches_the_config(page, console: ApiServer, bus: Bus) -> None:  # noqa: F811
    before = console.http.get("/api/config").json()
    page.fill("#safety-form input[name=gamma]", "12.5")
    page.click("#apply-safety")
    sync_api.expect(page.locator("#result")).to_contain_text("401")  # no token entered yet
    assert console.http.get("/api/config").json() == before

    page.fill("#token", TOKEN)
    page.fill("#operator", "grace")
    with FakeSafety(bus):
        page.fill("#safety-form input[name=gamma]", "12.5")
        page.click("#apply-safety")
        sync_api.expect(page.locator("#result")).to_contain_text("applied by the safety service")
    after = console.http.get("/api/config").json()
    assert after["safety"]["gamma"] == 12.5 and after["version"] == before["version"] + 1
    assert after["safety"]["phi"] == before["safety"]["phi"]  # only what was edited is sent
    assert console.http.get("/api/config/history").json()["entries"][0]["who"] == "grace"
    sync_api.expect(page.locator("#config-version")).to_have_text(f"v{after['version']}")
    sync_api.expect(page.locator("#history tbody tr").first).to_contain_text("safety.gamma")

    with FakeSafety(bus):  # one joint's acceleration bound: the whole vector is sent, the rest unchanged
        page.fill("#safety-form input[name='accel_max.2']", "45")
        page.click("#apply-safety")
        sync_api.expect(page.locator("#result")).to_contain_text("applied by the safety service")
    assert console.http.get("/api/config").json()["safety"]["accel_max"] == [*before["safety"]["accel_max"][:2], 45.0,
                                                                             *before["safety"]["accel_max"][3:]]

    with FakeSafety(bus):  # the retargeting method: only it is sent
        page.select_option("#retarget-form select[name=method]", "directions")
        page.click("#apply-retarget")
        sync_api.expect(page.locator("#result")).to_contain_text("applied by the safety service")
    history = console.http.get("/api/config/history").json()["entries"][0]
    assert console.http.get("/api/config").json()["retarget"]["method"] == "directions"
    assert "retargeting.method" in str(history) and "retargeting.scale" not in str(history)

    page.fill("#safety-form input[name=phi]", "7")  # out of range: the API's 422 names the field
    page.click("#apply-safety")
    sync_api.expect(page.locator("#result")).to_contain_text("phi:")
    assert console.http.get("/api/config").json()["safety"]["phi"] == before["safety"]["phi"]


def test_person_prediction_and_intrusion_response_in_the_form(page, console: ApiServer, bus: Bus) -> None:  # noqa: F811
    safety = console.http.get("/api/config").json()["safety"]
    form = "#safety-form "
    assert float(page.locator(form + "input[name=human_predict_s]").input_value()) == safety["human_predict_s"]
    assert page.locator(form + "select[name=on_intrusion]").input_value() == safety["on_intrusion"] == "stop"
    assert float(page.locator(form + "input[name=intrusion_backout_mps]").input_value()) == safety["intrusion_backout_mps"]
    with FakeSafety(bus, intrusion=True, ack=False):  # the default response: a protective stop
        sync_api.expect(page.locator("#intrusion")).to_have_text("yes: the robot stops")
        sync_api.expect(page.locator("#backing-out")).to_have_text("no")
        sync_api.expect(page.locator("#lateness")).to_have_text("0")
    with FakeSafety(bus, intrusion=True, ack=False, backing_out=True, lateness_ms=41.7):  # a still person, a late camera
        sync_api.expect(page.locator("#backing-out")).to_have_text("yes")
        sync_api.expect(page.locator("#lateness")).to_have_text("42")

    page.fill("#token", TOKEN)
    with FakeSafety(bus, intrusion=True):
        page.fill(form + "input[name=human_predict_s]", "0.05")
        page.select_option(form + "select[name=on_intrusion]", "retreat")
        page.fill(form + "input[name=intrusion_backout_mps]", "0")
        page.click("#apply-safety")
        sync_api.expect(page.locator("#result")).to_contain_text("applied by the safety service")
        sync_api.expect(page.locator("#intrusion")).to_have_text("yes: the robot retreats")
    after = console.http.get("/api/config").json()
    assert (after["safety"]["human_predict_s"], after["safety"]["on_intrusion"]) == (0.05, "retreat")
    assert after["safety"]["intrusion_backout_mps"] == 0.0
    changed = console.http.get("/api/config/history").json()["entries"][0]
    assert "safety.human_predict_s" in str(changed) and "safety.on_intrusion" in str(changed)
    assert "safety.intrusion_backout_mps" in str(changed)
    assert "safety.gamma" not in str(changed)  # only what was edited is sent

    with FakeSafety(bus):  # back to the default, from the form
        page.fill(form + "input[name=human_predict_s]", str(safety["human_predict_s"]))
        page.select_option(form + "select[name=on_intrusion]", "stop")
        page.fill(form + "input[name=intrusion_backout_mps]", str(safety["intrusion_backout_mps"]))
        page.click("#apply-safety")
        sync_api.expect(page.locator("#result")).to_contain_text("applied by the safety service")
    restored = console.http.get("/api/config").json()["safety"]
    assert (restored["human_predict_s"], restored["on_intrusion"]) == (safety["human_predict_s"], "stop")
    assert restored["intrusion_backout_mps"] == safety["intrusion_backout_mps"]


def test_feed_forward_and_target_path_in_the_form(page, console: ApiServer, bus: Bus) -> None:  # noqa: F811
    """Issue 17's imitation switches: the form shows the configured ones, sends only what was edited."""
    safety = console.http.get("/api/config").json()["safety"]
    form = "#safety-form "
    assert page.locator(form + "input[name=feedforward]").is_checked() is safety["feedforward"] is True
    assert page.locator(form + "select[name=target_path]").input_value() == safety["target_path"] == "jump"

    page.fill("#token", TOKEN)
    with FakeSafety(bus):
        page.uncheck(form + "input[name=feedforward]")
        page.select_option(form + "select[name=target_path]", "continuous")
        page.click("#apply-safety")
        sync_api.expect(page.locator("#result")).to_contain_text("applied by the safety service")
    after = console.http.get("/api/config").json()
    assert (after["safety"]["feedforward"], after["safety"]["target_path"]) == (False, "continuous")
    assert (after["config"]["safety"]["feedforward"], after["config"]["safety"]["target_path"]) == (False, "continuous")
    changed = str(console.http.get("/api/config/history").json()["entries"][0])
    assert "safety.feedforward" in changed and "safety.target_path" in changed and "safety.gamma" not in changed

    with FakeSafety(bus):  # back to the defaults, from the form
        page.check(form + "input[name=feedforward]")
        page.select_option(form + "select[name=target_path]", "jump")
        page.click("#apply-safety")
        sync_api.expect(page.locator("#result")).to_contain_text("applied by the safety service")
    restored = console.http.get("/api/config").json()["safety"]
    assert (restored["feedforward"], restored["target_path"]) == (True, "jump")


def test_calibrate_button(page, console: ApiServer, bus: Bus) -> None:  # noqa: F811
    page.fill("#token", TOKEN)
    theta = [0.0, 0.05, 0.1, 0.0, 0.3, 0.1, 0.0, 0.3]
    bus.publisher("human/state").put(human_state(theta))
    wait_until(lambda: (console.http.get("/api/status").json()["human_age_s"] or 1.0) < 0.3)
    page.click("#calibrate")
    sync_api.expect(page.locator("#result")).to_contain_text("calibration:")
    assert console.http.get("/api/config").json()["retarget"]["theta_home"] == pytest.approx(theta)
    assert float(page.locator("#retarget-form input[name='theta_home.4']").input_value()) == pytest.approx(0.3)
