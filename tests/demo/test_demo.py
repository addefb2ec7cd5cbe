"""``make demo``'s promise as the README states it (12 detections of its 6 flares, none that
matches no flare, the 6 events they make), and the vetting pages of those events
(``so-transients report``) in a real headless Chromium: Debian's ``chromium`` package, driven
by ``playwright`` (``.ci/run`` installs the browser where it is missing)."""
import contextlib
import functools
import http.server
import io
import re
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
from astropy.coordinates import SkyCoord
from astropy.io import fits
from astropy.stats import mad_std
from astropy.table import Table
from astropy.wcs import WCS

from so_transients import cli
from so_transients.score.person_labels import read_person_labels, with_person_labels
from so_transients.score.training import train_model

pytestmark = pytest.mark.slow    # simulates the demo's 10 minutes and runs the site pipeline

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
#: As a probe of this kind of machine starts it: no sandbox as root, and none of Chromium's
#: own background connections (a closed network refuses them).
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo run once (its printed report), its events' alerts and their vetting site."""
    root = tmp_path_factory.mktemp("demo")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert cli.main(["demo", "--out", str(root / "demo"), "--nproc", "2", "-q"]) == 0
        events = root / "demo" / "events"
        assert cli.main(["alerts", str(events), "-o", str(root / "alerts")]) == 0
        assert cli.main(["report", str(events), "-o", str(root / "site"), "--alerts",
                         str(root / "alerts"), "-q"]) == 0
    return dict(printed=printed.getvalue(), events=events, site=root / "site",
                alerts=root / "alerts", table=Table.read(events / "events.ecsv"))


def test_the_demo_reports_what_the_readme_promises(demo):
    out = demo["printed"]
    assert "12 detections, 0 not matching any injected flare." in out
    assert re.search(r"^6 event\(s\) from 12 detection\(s\)", out, re.M), out[-2000:]
    readme = (cli.DEMO_CONFIG.parents[2] / "README.md").read_text()
    assert "`12 detections, 0 not matching any injected flare.`" in readme
    assert "the 6 events of its 6 flares" in readme


def test_every_cutout_shows_its_flare_within_a_beam_of_the_fitted_position(demo):
    """Read as any FITS reader would: the brightest pixel of each event's cutout, placed on
    the sky by the file's own WCS, lies within one beam FWHM (BMAJ) of the event's fitted
    position; and every event has a cutout in each of its bands."""
    events = demo["table"]
    cutouts = Table.read(demo["events"] / "cutouts.ecsv")
    assert sorted(set(cutouts["event_id"])) == sorted(events["event_id"])
    for row in cutouts:
        event = events[events["event_id"] == row["event_id"]][0]
        with fits.open(demo["events"] / row["file"]) as hdus:
            sky, header = hdus[0].data, hdus[0].header
            assert header["BUNIT"] == "mJy" and hdus["WEIGHT"].data.shape == sky.shape
        wcs, fitted = WCS(header), SkyCoord(event["ra"], event["dec"], unit="deg")
        iy, ix = np.unravel_index(np.nanargmax(sky), sky.shape)
        assert wcs.pixel_to_world(ix, iy).separation(fitted).deg < header["BMAJ"], \
            (row["event_id"], row["bandpass"])
        # and stands out of the noise beyond a beam: pure noise in the ~400 pixels there
        # exceeds 5 sigma with a probability of 1e-4 (the demo's faintest: 6.6 sigma)
        y, x = np.mgrid[:sky.shape[0], :sky.shape[1]]
        away = np.isfinite(sky) & (wcs.pixel_to_world(x, y).separation(fitted).deg
                                   > header["BMAJ"])
        assert np.nanmax(sky) > 5 * mad_std(sky[away]), (row["event_id"], row["bandpass"])


@pytest.fixture(scope="module")
def browser():
    playwright_api = pytest.importorskip("playwright.sync_api")
    if not Path(CHROMIUM).is_file():
        pytest.fail(f"no Chromium at {CHROMIUM}: install Debian's `chromium` package "
                    "(.ci/run does)")
    with playwright_api.sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


class Watched:
    """A page with every request and console error recorded."""

    def __init__(self, browser, **options):
        self.context = browser.new_context(accept_downloads=True, **options)
        self.page = self.context.new_page()
        self.requests, self.errors = [], []
        self.page.on("request", lambda r: self.requests.append(r.url))
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error"
                     else None)
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.on("response", lambda r: self.errors.append(f"{r.status} {r.url}")
                     if r.status >= 400 else None)

    def images_loaded(self) -> list:
        """(src, loaded) of every image of the page."""
        return self.page.eval_on_selector_all(
            "img", "imgs => imgs.map(i => [i.getAttribute('src'), i.complete && "
                   "i.naturalWidth > 0])")


def _body_rows(page):
    return page.eval_on_selector_all(
        "#events tbody tr", "rows => rows.filter(r => r.style.display !== 'none')"
                            ".map(r => r.dataset.id)")


def test_the_vetting_pages_in_a_browser(demo, browser, tmp_path):
    site = demo["site"].resolve()
    events = demo["table"]
    w = Watched(browser)
    page = w.page
    page.goto(site.joinpath("index.html").as_uri())
    # one row per event, and nothing fetched from outside the folder
    assert sorted(map(int, _body_rows(page))) == sorted(events["event_id"])
    # sorting by S/N, then reversed
    snr = {str(e["event_id"]): e["peak_flux"] / e["peak_flux_err"] for e in events}
    page.click("#events th[data-key=snr]")
    assert _body_rows(page) == sorted(snr, key=snr.get)
    page.click("#events th[data-key=snr]")
    assert _body_rows(page) == sorted(snr, key=snr.get, reverse=True)
    # filtering: by S/N, by name, and back
    cut = float(np.median(list(snr.values())))
    page.fill("#filter-snr", f"{cut:.3f}")
    assert sorted(_body_rows(page)) == sorted(k for k, v in snr.items() if v >= cut)
    page.fill("#filter-snr", "0")
    page.fill("#filter-text", str(events["name"][2]))
    assert _body_rows(page) == [str(events["event_id"][2])]
    page.fill("#filter-text", "")
    assert len(_body_rows(page)) == len(events)
    # labels: two real, one artefact, one unsure, exported as a file train-score reads
    given = {0: "real", 1: "real", 2: "artefact", 3: "unsure"}
    for k, value in given.items():
        page.select_option(f"#events tr[data-id='{events['event_id'][k]}'] select.label", value)
    page.select_option("#filter-label", "real")
    assert sorted(_body_rows(page)) == sorted(str(events["event_id"][k]) for k in (0, 1))
    page.select_option("#filter-label", "")
    with page.expect_download() as download:
        page.click("#export-labels")
    exported = tmp_path / "labels.csv"
    download.value.save_as(exported)
    labels = read_person_labels(exported)
    expect = {str(events["event_uuid"][k]): int(value == "real") for k, value in given.items()
              if value != "unsure"}
    assert dict(zip(labels["event_uuid"], labels["label"])) == expect
    n_dets = {str(e["event_uuid"]): int(e["n_detections"]) for e in events}
    assert len(labels) == sum(n_dets[u] for u in expect)
    # ... and trains a score beside simulated candidates (here: the demo's own detections)
    simulated = Table.read(demo["events"] / "detections.ecsv")
    simulated["label"] = np.arange(len(simulated)) % 2
    both = with_person_labels(simulated, [exported])
    assert len(both) == len(simulated) + len(labels)
    model = train_model(both, both["label"], seed=0, version="test", n_trees=5)
    assert model.trained["n_real"] == int(np.sum(both["label"]))
    # every event page: its images load, its links stay in the folder, its alerts open
    for eid in events["event_id"]:
        page.goto(site.joinpath(f"events/event_{eid:04d}.html").as_uri())
        loaded = w.images_loaded()
        assert len(loaded) == 3 and all(ok for _, ok in loaded), (eid, loaded)
        alert_links = page.eval_on_selector_all("a[href*='alerts/']", "a => a.map(x => x.href)")
        assert len(alert_links) == 1, eid
        page.goto(alert_links[0])
        assert str(events["event_uuid"][events["event_id"] == eid][0]) in page.content()
    assert not w.errors, w.errors
    outside = [u for u in w.requests if not u.startswith((site.as_uri() + "/", "blob:", "data:"))]
    assert not outside, outside
    w.page.screenshot(path=str(tmp_path / "last_page.png"))
    w.context.close()


def test_the_vetting_pages_from_a_web_server(demo, browser):
    """The same folder served over HTTP: the index and an event page load with no error and
    no request to another host."""
    handler = functools.partial(http.server.SimpleHTTPRequestHandler,
                                directory=str(demo["site"]))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_port}"
    try:
        w = Watched(browser)
        w.page.goto(f"{base}/index.html")
        assert len(_body_rows(w.page)) == len(demo["table"])
        w.page.click("#events tbody tr a")
        w.page.wait_for_load_state()
        assert all(ok for _, ok in w.images_loaded())
        assert not w.errors, w.errors
        assert all(u.startswith((base + "/", "data:")) for u in w.requests), w.requests
        w.context.close()
    finally:
        server.shutdown()
