"""The service's page in a real headless Chromium (selenium): a street image is uploaded through the page's file
input and the answer is read back from the DOM: the top-k tiles, the confidence, the heading. A route's files are
chosen in the route player, which plays the track the service answers on a map of its tiles. A file name that is
HTML stays text; bad uploads show the service's error. Skips only where no Chromium / chromedriver is installed."""

from __future__ import annotations

import shutil
import time

import cv2
import httpx
import numpy as np
import pytest
from geoloc.apps.serve import create_app
from geoloc.sequence.odometry import odometry_text
from geoloc.sequence.particle_filter import FilterConfig
from helpers.calibrated import KNOWN, calibrated_copy
from test_localize import gallery  # noqa: F401  (a fixture: a 1-epoch TINY checkpoint and its saved gallery)
from test_serve import serving

from conftest import REALDATA

pytestmark = pytest.mark.slow
HOSTILE = "<img src=x onerror=alert(1)>.jpg"


def browser_paths() -> tuple[str, str]:
    browser = next(filter(None, map(shutil.which, ("chromium", "chromium-browser", "google-chrome"))), None)
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        pytest.skip("no Chromium and chromedriver on this machine (Debian: apt-get install chromium "
                    "chromium-driver; .ci/run installs them): the page's browser test needs a real browser")
    return browser, driver


@pytest.fixture(scope="module")
def browser():
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e .[dev])")
    from selenium.webdriver.chrome.service import Service

    binary, driver_path = browser_paths()
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                 "--window-size=1280,1100"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def page(gallery, tmp_path_factory):  # noqa: F811
    from geoloc.apps.localize import Localizer

    root, ckpt, folder = gallery
    calibrated = calibrated_copy(folder, tmp_path_factory.mktemp("page") / "gallery")
    localizer = Localizer.load(ckpt, calibrated, device="cpu")
    with serving(create_app(localizer, route=FilterConfig(particles=500))) as url:
        yield root, localizer, url


def ask(driver, url, image, **fields) -> None:
    """Open the page, choose `image` in its file input, fill the fields, press Localize, wait for the answer."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get(url + "/")
    driver.find_element(By.ID, "image").send_keys(str(image))
    for key, value in fields.items():
        box = driver.find_element(By.ID, key)
        box.clear()
        box.send_keys(str(value))
    driver.find_element(By.ID, "submit").click()
    WebDriverWait(driver, 60).until(lambda d: d.find_element(By.ID, "error").text
                                    or d.find_element(By.ID, "status").text.startswith("answered"))


def text(driver, element_id: str) -> str:
    return driver.find_element("id", element_id).get_attribute("textContent")


def shown_hits(driver) -> list[str]:
    return [li.get_attribute("textContent") for li in driver.find_elements("css selector", "#hits li")]


def test_the_page_uploads_an_image_and_shows_the_answer_with_a_hostile_file_name_as_text(page, browser, tmp_path):
    from selenium.common.exceptions import NoAlertPresentException

    root, localizer, url = page
    pano = max((root / "streetview" / "panos").glob("*.jpg"))
    hostile = tmp_path / HOSTILE
    shutil.copy(pano, hostile)
    ask(browser, url, hostile, heading=0, topk=3)
    assert text(browser, "error") == ""
    assert text(browser, "filename") == HOSTILE  # shown as text, never parsed
    assert browser.execute_script("return document.querySelectorAll('img[src=\"x\"], [onerror]').length") == 0
    with pytest.raises(NoAlertPresentException):
        browser.switch_to.alert.text
    from geoloc.apps.localize import read_street

    direct = localizer.localize(read_street(hostile), topk=3, heading=0.0, name=HOSTILE)
    hits = shown_hits(browser)
    assert len(hits) == 3
    # the tiles are on the page, not inside another element that shares an id (the list once had the form's
    # "topk" id, so its items went into the number field, present but never drawn)
    assert browser.execute_script("const ids = [...document.querySelectorAll('[id]')].map(e => e.id);"
                                  "return ids.length === new Set(ids).size")
    assert all(li.is_displayed() and li.size["height"] > 0
               for li in browser.find_elements("css selector", "#hits li"))
    for hit, row in zip(hits, direct.topk):
        assert f"#{row['rank']} score {row['score']:.3f}" in hit and row["path"] in hit
    assert text(browser, "confidence").startswith(f"{100 * direct.confidence:.1f}%")
    assert direct.confidence == pytest.approx(float(KNOWN.probability(
        [[direct.topk[0]["score"], direct.topk[0]["score"] - direct.topk[1]["score"]]])[0]))
    assert text(browser, "status") == f"answered {HOSTILE}"
    # the tiles come from the service's /tiles route and load
    time.sleep(0.5)
    loaded = browser.execute_script("return [...document.querySelectorAll('#hits img')].map(i => i.naturalWidth)")
    assert len(loaded) == 3 and all(width > 0 for width in loaded)
    browser.set_window_size(1280, 1400)  # the whole answer, top-k tiles included
    browser.save_screenshot(str(tmp_path / "page.png"))  # the page as the test left it (pytest keeps the folder)
    browser.set_window_size(1280, 1100)


def test_the_page_shows_a_real_panorama_answered_with_a_searched_heading_as_uncalibrated(page, browser):
    pano = REALDATA / "cvusa_mini" / "streetview" / "panos" / "0000001.jpg"
    if not pano.is_file():
        pytest.skip(f"the real CVUSA sample {pano} is not on this machine (../shared/realdata)")
    ask(browser, page[2], pano, heading="search")  # a north-aligned checkpoint searches only when asked
    assert text(browser, "error") == ""
    assert len(shown_hits(browser)) == 5
    assert text(browser, "confidence").startswith("uncalibrated")
    assert "(search)" in text(browser, "heading-out")


def test_the_page_shows_why_an_upload_or_a_setting_is_refused(page, browser, tmp_path):
    url = page[2]
    notes = tmp_path / "notes.txt"
    notes.write_text("not an image")
    ask(browser, url, notes)
    assert text(browser, "error") == "notes.txt is not a JPEG or PNG image (it is text/plain): choose a street image"
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(cv2.imencode(".jpg", np.full((32, 128, 3), 90, np.uint8))[1].tobytes()[:300])
    ask(browser, url, cut)
    assert text(browser, "error").startswith("415: the upload 'cut.jpg' is not an image")
    pano = max((page[0] / "streetview" / "panos").glob("*.jpg"))
    ask(browser, url, pano, abstain=2)
    assert text(browser, "error").startswith("422: form field abstain=") and "[0, 1]" in text(browser, "error")
    ask(browser, url, pano, heading_prior=20)
    assert "given without heading" in text(browser, "error")


def route_files(root, folder, names, rows: int | None = None) -> list:
    """Frames `names` in `folder` (copies of the dataset's panoramas) and an odometry.csv of `rows` rows (default:
    one a frame, 10 m apart, a turn of 5 degrees each); the paths, the odometry last."""
    panos = sorted((root / "streetview" / "panos").glob("*.jpg"))
    folder.mkdir()
    for name, pano in zip(names, panos):
        shutil.copy(pano, folder / name)
    count = len(names) if rows is None else rows
    (folder / "odometry.csv").write_text(odometry_text([0.0] + [10.0] * (count - 1), [0.0] + [5.0] * (count - 1)))
    return [folder / name for name in names] + [folder / "odometry.csv"]


def choose_route(driver, url, files) -> None:
    """Open the page and choose `files` in the route player's file input, all at once."""
    driver.get(url + "/")
    driver.find_element("id", "route-files").send_keys("\n".join(map(str, files)))


def follow(driver, url, files) -> None:
    """Choose `files` in the route player, press its button, wait for the track or the error."""
    from selenium.webdriver.support.ui import WebDriverWait

    choose_route(driver, url, files)
    driver.find_element("id", "route-submit").click()
    WebDriverWait(driver, 120).until(lambda d: text(d, "route-error")
                                     or text(d, "route-status").startswith("followed"))


def posted_route(url, files) -> dict:
    """The service's answer to the route's files as the page sends them: frames in name order, the page's settings."""
    frames = sorted((f for f in files if f.suffix == ".jpg"), key=lambda f: f.name)
    odometry = next(f for f in files if f.suffix == ".csv")
    sent = [("frames", (f.name, f.read_bytes(), "image/jpeg")) for f in frames]
    sent.append(("odometry", (odometry.name, odometry.read_bytes(), "text/csv")))
    response = httpx.post(url + "/localize/route", files=sent, data={"fov": "360", "topk": "5"}, timeout=120)
    assert response.status_code == 200, response.text
    return response.json()


def drawn(driver, name: str) -> str | None:
    return driver.find_element("id", "route-map").get_attribute(f"data-{name}")


def test_the_route_player_plays_the_services_track_on_its_tiles(page, browser, tmp_path):
    from selenium.webdriver.support.ui import WebDriverWait

    root, _, url = page
    files = route_files(root, tmp_path / "route", [f"frame_{i:03d}.jpg" for i in range(3)])
    follow(browser, url, list(reversed(files)))  # the order chosen does not matter: frames go in name order
    assert text(browser, "route-error") == ""
    assert text(browser, "route-status") == "followed 3 frames"
    slider = browser.find_element("id", "route-frame")
    assert (slider.get_attribute("min"), slider.get_attribute("max")) == ("0", "2")
    assert drawn(browser, "frame") == "0" and text(browser, "route-estimate").startswith("frame_000.jpg (frame 1 of 3)")
    browser.find_element("id", "route-play").click()
    WebDriverWait(browser, 10).until(lambda d: drawn(d, "frame") == "2" and text(d, "route-play") == "Play")
    expected = posted_route(url, files)  # the filter is seeded: the same files give the same track
    last = expected["frames"][2]
    assert text(browser, "route-estimate").startswith(
        f"frame_002.jpg (frame 3 of 3): x {last['position']['x_m']:.1f} m, y {last['position']['y_m']:.1f} m, "
        f"heading {last['heading_deg']:.1f}° from north; 95% region ")
    assert text(browser, "route-estimate").endswith(f"; tracked mass {last['tracked_mass']:.3f}")
    # every tile the answer names is drawn once its image has loaded (this gallery has no extents: squares)
    assert all(set(tile) == {"row", "x_m", "y_m", "extent_m"} and tile["extent_m"] is None
               for tile in expected["tiles"])
    WebDriverWait(browser, 10).until(lambda d: drawn(d, "tiles-drawn") == str(len(expected["tiles"])))
    assert int(drawn(browser, "tiles-drawn")) > 0
    painted = browser.execute_script(
        "const c = document.getElementById('route-map'); const d = c.getContext('2d').getImageData(0, 0, c.width, "
        "c.height).data; let n = 0; for (let i = 0; i < d.length; i += 4) if (d[i] < 250 || d[i + 1] < 250 || "
        "d[i + 2] < 250) n++; return [n, c.width * c.height];")
    assert painted[0] > 0.05 * painted[1], painted  # tiles and track, not a blank canvas
    browser.set_window_size(1280, 1800)  # the route player below the single-image form
    browser.save_screenshot(str(tmp_path / "route.png"))  # the played route (pytest keeps the folder)
    browser.set_window_size(1280, 1100)


def test_the_route_player_shows_a_hostile_frame_name_as_text(page, browser, tmp_path):
    from selenium.common.exceptions import NoAlertPresentException

    root, _, url = page
    follow(browser, url, route_files(root, tmp_path / "route", [HOSTILE, "frame_001.jpg", "frame_002.jpg"]))
    assert text(browser, "route-error") == ""
    assert text(browser, "route-estimate").startswith(f"{HOSTILE} (frame 1 of 3): ")  # "<" sorts first
    assert browser.execute_script("return document.querySelectorAll('img[src=\"x\"], [onerror]').length") == 0
    with pytest.raises(NoAlertPresentException):
        browser.switch_to.alert.text


def test_the_route_player_says_why_a_route_is_refused(page, browser, tmp_path):
    root, _, url = page
    files = route_files(root, tmp_path / "route", [f"frame_{i:03d}.jpg" for i in range(3)])
    choose_route(browser, url, files[:3])  # the frames without their odometry.csv
    assert text(browser, "route-error") == ("no odometry: choose the route's odometry.csv "
                                            "(frame,distance_m,heading_change_deg) together with its frames")
    browser.find_element("id", "route-submit").click()
    assert text(browser, "route-error").startswith("no odometry")
    assert browser.find_element("id", "route-result").get_attribute("hidden") is not None  # nothing was sent
    choose_route(browser, url, files[3:])  # the odometry alone
    assert text(browser, "route-error") == "no frames: choose the route's JPEG or PNG frames together with odometry.csv"
    truth, other = tmp_path / "route" / "truth.csv", tmp_path / "other.csv"
    truth.write_text("lat,lon\n")
    other.write_text("frame,distance_m,heading_change_deg\n")
    choose_route(browser, url, [*files, truth])  # a synthetic route's folder: odometry.csv is the odometry
    assert text(browser, "route-error") == ""
    assert text(browser, "route-status") == "3 frames and odometry.csv (left out: truth.csv)"
    choose_route(browser, url, [*files[:3], truth, other])
    assert text(browser, "route-error") == ("2 .csv files (other.csv, truth.csv), none of them named odometry.csv: "
                                            "choose the route's one odometry file together with its frames")
    short = route_files(root, tmp_path / "short", [f"frame_{i:03d}.jpg" for i in range(3)], rows=2)
    follow(browser, url, short)  # the service's 400, shown as the single-image form shows its errors
    assert text(browser, "route-error").startswith("400: the odometry has 2 rows for 3 frames")
