#!/usr/bin/env python
"""Render an HTML report in headless Chromium and check that every <img> loads.

Usage: python tools/check_report_chromium.py REPORT.html [--chromium PATH] [--timeout S]

A copy of the page with a small script appended is written beside the report
(so relative image links resolve), Chromium loads it from file:// offline and
dumps the DOM after the load event; the script writes, into the DOM, the
number of <img> elements and those with ``naturalWidth == 0`` (not loaded).
Exit status: 0 all images load, 1 some do not (listed), 2 Chromium is missing
or failed. Importable: :func:`check_report`, :func:`find_chromium`.
"""

from __future__ import annotations

import argparse
import html
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")

_CHECK_JS = """
<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var bad = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); })
                .map(function (i) { return i.getAttribute('src'); });
  var pre = document.createElement('pre');
  pre.id = 'mehs-image-check';
  var tag = 'MEHS' + 'CHECK';  // split so the script's own text never matches
  pre.textContent = tag + JSON.stringify({images: imgs.length, broken: bad}) + tag;
  document.body.appendChild(pre);
});
</script>
"""


def find_chromium() -> str | None:
    """Path of a Chromium/Chrome executable on PATH, or None."""
    for name in CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    return None


def check_report(html_path: str | Path, chromium: str | None = None,
                 timeout: float = 120) -> dict:
    """Load ``html_path`` in headless Chromium; return ``{"images": n, "broken": [src, ...]}``.

    Raises
    ------
    FileNotFoundError
        No Chromium found.
    RuntimeError
        Chromium failed or produced no check result.
    """
    html_path = Path(html_path).resolve()
    chromium = chromium or find_chromium()
    if not chromium:
        raise FileNotFoundError("chromium not found on PATH")
    text = html_path.read_text(encoding="utf-8")
    text = text.replace("</body>", _CHECK_JS + "</body>") if "</body>" in text else text + _CHECK_JS
    fd, probe = tempfile.mkstemp(prefix=f".{html_path.stem}.", suffix=".check.html",
                                 dir=html_path.parent)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(text)
    profile = tempfile.mkdtemp(prefix="mehs-chromium-")
    try:
        cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu",
               "--disable-background-networking", "--disable-dev-shm-usage",
               "--no-first-run", "--allow-file-access-from-files",
               f"--user-data-dir={profile}", "--virtual-time-budget=10000",
               "--dump-dom", Path(probe).as_uri()]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    finally:
        os.unlink(probe)
        shutil.rmtree(profile, ignore_errors=True)
    m = re.search(r"MEHSCHECK(.*?)MEHSCHECK", proc.stdout, re.S)
    if not m:
        raise RuntimeError(f"chromium gave no check result (exit {proc.returncode}): "
                           f"{proc.stderr.strip()[-800:]}")
    return json.loads(html.unescape(m.group(1)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("html")
    ap.add_argument("--chromium", default=None)
    ap.add_argument("--timeout", type=float, default=120)
    args = ap.parse_args(argv)
    try:
        res = check_report(args.html, args.chromium, args.timeout)
    except (FileNotFoundError, RuntimeError, subprocess.TimeoutExpired) as exc:
        print(f"check_report_chromium: {exc}", file=sys.stderr)
        return 2
    print(f"{args.html}: {res['images']} images, {len(res['broken'])} not loaded")
    for src in res["broken"]:
        print(f"  broken: {src}")
    return 0 if res["images"] > 0 and not res["broken"] else 1


if __name__ == "__main__":
    sys.exit(main())
