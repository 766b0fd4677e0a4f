"""Regenerate the documentation's picture of the live viewer (docs/img/viewer.png) from a short run.

Simulates a city sequence (``ti-cmax simulate``), runs ``ti-cmax slam --save-recording`` on it, serves the recording
with rerun's web viewer on localhost (``rerun --serve-web``), opens it in headless Chromium (Playwright driving the
system's Chromium, software WebGL: no GPU needed), waits until the rendered page stops changing, takes the screenshot,
stops the server and writes the picture downscaled to ``--width`` pixels.

    python examples/viewer_screenshot.py [--recording FILE.rrd] [--out docs/img/viewer.png] [--width 1200]

Needs the viewer extra (``pip install -e ".[viewer]"``), ``pip install playwright`` and a Chromium (Debian:
``apt-get install chromium``; or ``--browser PATH``, or ``playwright install chromium``). ``--recording`` shows an
existing recording instead of making one.
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import quote

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM_FLAGS = ["--no-sandbox", "--use-angle=swiftshader", "--use-gl=angle", "--enable-unsafe-swiftshader",
                  "--ignore-gpu-blocklist"]  # WebGL on the CPU (SwiftShader), which the web viewer renders with


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_port(port: int, timeout: float) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise RuntimeError(f"nothing listens on port {port} after {timeout} s")


def record(work: Path) -> Path:
    """A 1.5 s simulated city sequence through ``slam --save-recording``; the recording's path."""
    ti_cmax = str(Path(sys.executable).with_name("ti-cmax"))
    seq, rrd = work / "seq", work / "run.rrd"
    subprocess.run([ti_cmax, "simulate", str(seq), "--scene", "city", "--duration", "1.5", "--quiet"], check=True)
    subprocess.run([ti_cmax, "slam", str(seq), "--out", str(work / "slam"), "--save-recording", str(rrd),
                    "--quiet"], check=True)
    return rrd


def screenshot(rrd: Path, browser: str | None, size=(1600, 1000), settle: float = 6.0,
               timeout: float = 180.0) -> bytes:
    """The PNG of rerun's web viewer showing ``rrd``, taken once the page has looked the same for ``settle`` seconds
    (the viewer has fetched and drawn the whole recording)."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        raise SystemExit("viewer_screenshot.py needs Playwright: pip install playwright") from None
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if rerun is None:
        raise SystemExit('viewer_screenshot.py needs rerun: pip install -e ".[viewer]"')
    web, grpc = free_port(), free_port()
    # its own process group: the ``rerun`` command may be a launcher whose child is the server
    server = subprocess.Popen([rerun, "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web),
                               "--port", str(grpc), str(rrd)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)
    try:
        wait_for_port(web, 30.0)
        url = f"http://127.0.0.1:{web}/?url={quote(f'rerun+http://127.0.0.1:{grpc}/proxy', safe='')}"
        with sync_playwright() as p:
            chromium = p.chromium.launch(executable_path=browser, headless=True, args=CHROMIUM_FLAGS)
            page = chromium.new_page(viewport={"width": size[0], "height": size[1]})
            page.goto(url)
            end, last, same_since = time.monotonic() + timeout, None, time.monotonic()
            while True:
                time.sleep(1.0)
                shot = page.screenshot()
                now = time.monotonic()
                if shot != last:
                    last, same_since = shot, now
                elif now - same_since >= settle:
                    break
                if now > end:
                    raise RuntimeError(f"the viewer kept changing for {timeout} s")
            chromium.close()
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=10)
    return last


def write_scaled(data: bytes, png: Path, width: int) -> None:
    """The PNG ``data`` downscaled to ``width`` pixels (if wider), written as an optimised palette PNG."""
    import io

    from PIL import Image

    image = Image.open(io.BytesIO(data)).convert("RGB")
    if image.width > width:
        image = image.resize((width, round(image.height * width / image.width)), Image.LANCZOS)
    png.parent.mkdir(parents=True, exist_ok=True)
    image.quantize(256).save(png, optimize=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recording", type=Path, default=None, help="an existing .rrd to show (default: make one)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "viewer.png")
    ap.add_argument("--width", type=int, default=1200, help="width of the written picture (px)")
    ap.add_argument("--browser", default=None, help="Chromium executable (default: chromium on PATH, else "
                                                     "Playwright's own)")
    args = ap.parse_args(argv)
    browser = args.browser or shutil.which("chromium") or shutil.which("chromium-browser")
    with tempfile.TemporaryDirectory() as tmp:
        rrd = args.recording or record(Path(tmp))
        write_scaled(screenshot(rrd, browser), args.out, args.width)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
