"""The documentation site: it builds strictly (every cross-reference resolves, no missing
page), documents every public name, has no broken link inside the site, and renders in a real
browser (headless Chromium, where installed) with every image and script it asks for served."""

import functools
import http.server
import os
import re
import shutil
import subprocess
import sys
import threading
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

import jaxdyn

ROOT = Path(__file__).resolve().parents[1]


@functools.cache
def _site(tmp: str) -> Path:
    site = Path(tmp) / "site"
    env = {**os.environ, "JAXDYN_DOCS_EXECUTE": "false", "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d",
                           str(site)], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return site


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    pytest.importorskip("mkdocs", reason="the docs extra is not installed")
    return _site(str(tmp_path_factory.mktemp("docs")))


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.links = []

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name in ("href", "src") and value:
                self.links.append(value)


def test_every_public_name_has_one_api_entry():
    entries = re.findall(r"^::: jaxdyn\.(\w+)$",
                         "\n".join(p.read_text() for p in (ROOT / "docs" / "api").glob("*.md")),
                         re.M)
    assert sorted(entries) == sorted(jaxdyn.__all__)


def test_site_builds_strictly_with_every_page(site):
    for page in ("index.html", "api/scenes/index.html", "guides/command/index.html",
                 "notebooks/02_torque_free_polhode/index.html"):
        assert (site / page).is_file(), page
    api = (site / "api" / "simulate" / "index.html").read_text()
    assert "jaxdyn.simulate" in api and "Raises" in api
    # The parameter tables come from the declarations (through the README's generated block).
    assert "linear-damping" in (site / "guides" / "command" / "index.html").read_text()


def test_no_broken_link_inside_the_site(site):
    broken = []
    for page in site.rglob("*.html"):
        parser = _Links()
        parser.feed(page.read_text())
        for link in parser.links:
            url = urlparse(link)
            if url.scheme or url.netloc or link.startswith(("#", "mailto:", "data:")):
                continue
            path = unquote(url.path)
            target = (site / path.lstrip("/") if path.startswith("/")
                      else page.parent / path).resolve()
            if target.is_dir():
                target = target / "index.html"
            if not target.exists():
                broken.append(f"{page.relative_to(site)} -> {link}")
    assert not broken, broken[:20]


def _chromium() -> str | None:
    return next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                 if shutil.which(n)), None)


def test_pages_render_in_a_browser(site, tmp_path):
    browser = _chromium()
    if browser is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install chromium); the "
                    "browser check is skipped")
    requests: list[tuple[str, int]] = []

    class Handler(http.server.SimpleHTTPRequestHandler):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, directory=str(site), **kwargs)

        def log_request(self, code="-", size="-"):
            requests.append((self.path, int(code) if str(code).isdigit() else 0))

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        for page, text in (("", "Getting started"), ("api/simulate/", "jaxdyn.simulate"),
                           ("notebooks/01_falling_rod/", "falling rod")):
            shot = tmp_path / (page.strip("/").replace("/", "_") or "home")
            # One launch per page both draws it and dumps its DOM after the scripts ran.
            proc = subprocess.run(
                [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                 f"--screenshot={shot}.png", "--window-size=1280,1600",
                 "--virtual-time-budget=5000", "--dump-dom", f"{base}/{page}"],
                capture_output=True, text=True, timeout=120)
            assert proc.returncode == 0 and Path(f"{shot}.png").stat().st_size > 20_000, \
                proc.stderr[-2000:]
            dom = proc.stdout
            assert text.lower() in dom.lower(), page
    finally:
        server.shutdown()
    local = [(path, code) for path, code in requests if not path.startswith("/search")]
    failed = [(path, code) for path, code in local if code >= 400]
    assert not failed, failed
    # Every image the pages ask for is served (the notebooks' figures where executed).
    assert any(path.endswith((".css", ".js")) for path, _ in local)
