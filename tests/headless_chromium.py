"""Open a local HTML file in headless Chromium: screenshot, DOM and JavaScript errors.

Used by the viewer, report and published-folder tests. Debian's ``chromium`` (installed by
``scripts/system-deps.sh``) runs with a fresh profile, no network services
and software WebGL (SwiftShader, opted in with ``--enable-unsafe-swiftshader``
because the page is our own). JavaScript errors are collected by an
``error``/``unhandledrejection`` hook injected at the top of a copy of the
page, which writes them into a ``<pre id="t3d-js-errors">`` element that the
dumped DOM shows; console messages that Chromium logs to stderr are
returned too.
"""

from __future__ import annotations

import html
import re
import shutil
import subprocess
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
from PIL import Image

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")

needs_chromium = pytest.mark.skipif(
    CHROMIUM is None,
    reason="headless Chromium is not installed (Debian package 'chromium'; "
    "scripts/system-deps.sh installs it)",
)

FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--enable-unsafe-swiftshader",
    "--hide-scrollbars",
    "--enable-logging=stderr",
    "--v=0",
]

_HOOK = (
    "<script>(function(){var errs=[];function show(){var p=document.getElementById("
    "'t3d-js-errors');if(!p){p=document.createElement('pre');p.id='t3d-js-errors';"
    "(document.body||document.documentElement).appendChild(p);}p.textContent=errs.join('\\n');}"
    "window.addEventListener('error',function(e){errs.push('error: '+(e.message||e.type)+' @ '"
    "+(e.filename||(e.target&&(e.target.src||e.target.href))||''));show();},true);"
    "window.addEventListener('unhandledrejection',function(e){errs.push('rejection: '+e.reason);"
    "show();});var ce=console.error;console.error=function(){errs.push('console.error: '+"
    "Array.prototype.join.call(arguments,' '));show();return ce.apply(console,arguments);};"
    "document.addEventListener('DOMContentLoaded',show);"
    "window.addEventListener('load',function(){var p=document.createElement('pre');"
    "p.id='t3d-images';var out=[];for(var i=0;i<document.images.length;i++){"
    "var im=document.images[i];out.push(im.naturalWidth+' '+im.getAttribute('src'));}"
    "p.textContent=out.join('\\n');document.body.appendChild(p);});})();</script>"
)


@dataclass
class PageResult:
    screenshot: np.ndarray  # (h, w, 3) uint8
    dom: str
    js_errors: list[str]
    console: list[str]
    #: (src attribute, naturalWidth) of every <img> once the page has loaded
    images: list[tuple[str, int]]


def _run(args: list[str], profile: Path, timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run(
        [CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def open_page(
    html_path: Path, tmp_path: Path, *, size=(900, 700), budget_ms=15000, timeout=180.0
) -> PageResult:
    """Load ``html_path`` (a copy with the error hook) and return what the browser shows."""
    text = Path(html_path).read_text(encoding="utf-8")
    head = re.search(r"<head[^>]*>", text, flags=re.IGNORECASE)
    hooked = text[: head.end()] + _HOOK + text[head.end() :] if head else _HOOK + text
    page = html_path.parent / f"_hooked_{html_path.name}"
    page.write_text(hooked, encoding="utf-8")
    url = page.resolve().as_uri()
    shot = tmp_path / "screenshot.png"
    common = [f"--window-size={size[0]},{size[1]}", f"--virtual-time-budget={budget_ms}"]
    # one browser for both: the screenshot and the DOM of the same page, after the same budget
    r1 = _run([*common, f"--screenshot={shot}", "--dump-dom", url], tmp_path / "profile1", timeout)
    assert shot.is_file(), f"chromium wrote no screenshot: {r1.stderr[-2000:]}"
    with Image.open(shot) as im:
        pixels = np.asarray(im.convert("RGB"))
    dom, stderr = r1.stdout, r1.stderr
    if "</html>" not in dom.lower():  # a Chromium that does not combine them: a second run
        r2 = _run([*common, "--dump-dom", url], tmp_path / "profile2", timeout)
        dom, stderr = r2.stdout, r1.stderr + r2.stderr
    match = re.search(r'<pre id="t3d-js-errors">(.*?)</pre>', dom, flags=re.DOTALL)
    errors = [e for e in (match.group(1).splitlines() if match else []) if e.strip()]
    console = [ln for ln in stderr.splitlines() if "CONSOLE" in ln]
    match = re.search(r'<pre id="t3d-images">(.*?)</pre>', dom, flags=re.DOTALL)
    images = []
    for line in match.group(1).splitlines() if match else []:
        width, _, src = line.partition(" ")
        images.append((html.unescape(src), int(width)))
    return PageResult(screenshot=pixels, dom=dom, js_errors=errors, console=console, images=images)


class _Links(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.targets: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag in ("img", "script") and a.get("src"):
            self.targets.append(a["src"])
        if tag in ("a", "link") and a.get("href"):
            self.targets.append(a["href"])


def local_links(html_path: Path) -> list[str]:
    """Every src/href of the page (images, scripts, links)."""
    parser = _Links()
    parser.feed(Path(html_path).read_text(encoding="utf-8"))
    return parser.targets


def unresolved_links(html_path: Path) -> list[str]:
    """Links that are not relative paths to existing files beside the page."""
    bad = []
    root = Path(html_path).parent
    for target in local_links(html_path):
        path = unquote(target.split("#")[0])
        if not path or "://" in target or target.startswith(("/", "data:", "javascript:")):
            bad.append(target)
        elif not (root / path).is_file():
            bad.append(target)
    return bad


def serious_console_messages(console: list[str]) -> list[str]:
    """Console lines that report a failure (uncaught errors, failed loads)."""
    bad = re.compile(
        r"Uncaught|TypeError|ReferenceError|SyntaxError|Failed to load|"
        r"net::ERR_",
        re.IGNORECASE,
    )
    return [ln for ln in console if bad.search(ln)]
