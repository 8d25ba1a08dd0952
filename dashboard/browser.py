"""A dashboard URL opened in Debian's headless Chromium, driven by Playwright (tests, benchmarks).

Uses the system browser (/usr/bin/chromium, `apt-get install chromium`), never a downloaded one,
with a fresh profile per page; `max_fps` caps the page's animation frames (see _cap_fps_script). Console errors and uncaught
page errors are collected, so a check
can insist on none. Playwright is a development dependency, imported only here.
"""

from __future__ import annotations

import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-gpu-compositing", "--disable-accelerated-2d-canvas",
]


def chromium_available() -> bool:
    """Whether Playwright's Python package and the system Chromium are both installed."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return False
    return Path(CHROMIUM).exists()


class BrowserPage:
    """One headless Chromium page on `url`; `errors` collects console errors and page errors."""

    def __init__(
        self, url: str, viewport: tuple[int, int] = (1400, 900), max_fps: float | None = None, nice: int = 0, timeout_s: float = 30.0
    ) -> None:
        """`timeout_s`: how long any one browser action (a click, a screenshot, a wait) may take; a
        niced browser on a machine the rig keeps busy draws a frame in seconds, not milliseconds.
        `nice` > 0 runs the browser (all its processes and threads) at that lower CPU priority: on
        a machine it shares with the simulated rig, an observer must not starve what it observes.
        Run as root, Chromium resets its children to niceness 0 and raises its display threads to
        -8, ahead of the rig; it is therefore started without CAP_SYS_NICE (util-linux `setpriv`),
        so it can only keep the niceness it was given."""
        from playwright.sync_api import sync_playwright

        self.url = url
        self.errors: list[str] = []
        self.console: list[tuple[str, str]] = []
        self.context: Any = None
        self._profile = tempfile.mkdtemp(prefix="bagit-chromium-")
        executable = CHROMIUM
        if nice > 0:  # a launcher: lower priority, and no capability to raise it again
            executable = str(Path(self._profile).parent / f"{Path(self._profile).name}-nice.sh")
            Path(executable).write_text(f'#!/bin/sh\nexec setpriv --bounding-set -sys_nice --inh-caps -sys_nice nice -n {int(nice)} {CHROMIUM} "$@"\n')
            Path(executable).chmod(0o755)
        self._launcher = executable if executable != CHROMIUM else None
        self._pw = sync_playwright().start()
        try:
            self.context = self._pw.chromium.launch_persistent_context(
                self._profile, executable_path=executable, headless=True, args=CHROMIUM_ARGS,
                viewport={"width": viewport[0], "height": viewport[1]},
            )
            self.context.set_default_timeout(timeout_s * 1000)
            self.page = self.context.new_page()
            if max_fps is not None:
                self.page.add_init_script(_cap_fps_script(max_fps))
            self.page.on("console", self._on_console)
            self.page.on("pageerror", lambda e: self.errors.append(f"pageerror: {e}"))
            self.page.goto(url)
        except BaseException:
            self.close()
            raise

    def _on_console(self, m: Any) -> None:
        if len(self.console) < 1000:
            self.console.append((m.type, m.text))
        if m.type == "error":
            self.errors.append(f"console: {m.text}")

    def wait_text(self, text: str, timeout_s: float = 20.0) -> None:
        self.page.get_by_text(text).first.wait_for(timeout=timeout_s * 1000)

    def click_button(self, name: str) -> None:
        self.page.get_by_role("button", name=name, exact=True).click()

    def settle(self, seconds: float = 1.5) -> None:
        """Let the browser draw what the server sent (a screenshot right after a change may miss it)."""
        self.page.wait_for_timeout(seconds * 1000)

    def toggle_layer(self, label: str) -> None:
        """Click a layer's checkbox in the View folder (opening the folder when it is closed)."""
        box = self.page.get_by_label(label, exact=True)
        if not box.is_visible():
            self.page.get_by_text("View", exact=True).click()
        box.click()

    def select(self, label: str, option: str) -> None:
        """Pick `option` in the dropdown labelled `label` (e.g. the panel's Scenario picker)."""
        self.page.get_by_label(label, exact=True).click()
        self.page.get_by_role("option", name=option, exact=True).click()

    def options(self, label: str) -> list[str]:
        """The options of the dropdown labelled `label` (opens it, reads them, closes it again)."""
        self.page.get_by_label(label, exact=True).click()
        opts = self.page.get_by_role("option")
        opts.first.wait_for()
        out = [opts.nth(i).inner_text().strip() for i in range(opts.count())]
        self.page.keyboard.press("Escape")
        return out

    def panel_text(self, marker: str = "Stage:") -> str:
        """The text of the panel paragraph holding `marker` (the run state: run id, stage, reason, e-stop)."""
        p = self.page.locator("p", has_text=marker).first
        return p.inner_text() if p.count() else ""

    def stage(self) -> str | None:
        """The run's stage as the panel shows it (`**Stage:** done · 100 % · ...`), None before it shows one."""
        m = re.search(r"Stage:\s*([a-z-]+)", self.panel_text("Stage:"))
        return m.group(1) if m else None

    def wait_stage(self, stages: str | tuple[str, ...], timeout_s: float = 60.0, poll_s: float = 0.25) -> str | None:
        """Poll the panel until its stage is one of `stages`; the last stage seen (check it)."""
        want = (stages,) if isinstance(stages, str) else tuple(stages)
        deadline = time.monotonic() + timeout_s
        seen = self.stage()
        while seen not in want and time.monotonic() < deadline:
            self.page.wait_for_timeout(poll_s * 1000)
            seen = self.stage()
        return seen

    def dismiss_notifications(self) -> int:
        """Close the page's pop-up notifications (e.g. viser's "software WebGL" warning), so a
        screenshot shows the scene; how many were closed."""
        buttons = self.page.locator(".mantine-Notification-closeButton")
        n = buttons.count()
        for i in reversed(range(n)):
            try:
                buttons.nth(i).click(timeout=2000)
            except Exception:  # noqa: BLE001 - one that closed by itself meanwhile
                pass
        return n

    def table_rows(self) -> list[list[str]]:
        """Every table row of the page (the health and history tables) as its cells' texts."""
        rows = self.page.locator("tr")
        return [[c.strip() for c in rows.nth(i).locator("td").all_inner_texts()] for i in range(rows.count())]

    def screenshot(self, path: str | Path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        self.page.screenshot(path=str(p))
        return p

    def canvas_pixels(self) -> np.ndarray:
        """The 3-D view as an (H, W, 3) uint8 RGB array."""
        import cv2

        png = self.page.locator("canvas").first.screenshot()
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise RuntimeError("the canvas screenshot did not decode as an image")
        return np.ascontiguousarray(img[:, :, ::-1])

    def js_heap_mb(self) -> float | None:
        """Chromium's used JS heap (MB), or None when the browser does not report it."""
        v = self.page.evaluate("() => (performance.memory ? performance.memory.usedJSHeapSize : null)")
        return None if v is None else float(v) / 1e6

    def close(self) -> None:
        try:
            if self.context is not None:
                self.context.close()
        finally:
            self._pw.stop()
            shutil.rmtree(self._profile, ignore_errors=True)
            if self._launcher is not None:
                Path(self._launcher).unlink(missing_ok=True)

    def __enter__(self) -> BrowserPage:
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()


def _cap_fps_script(max_fps: float) -> str:
    """JS run before the page's own: requestAnimationFrame fires at most `max_fps` times a second.

    Software WebGL redraws the 3-D view on every animation frame (about 0.6 of a core for a still
    scene); on a small machine shared with the simulated rig a capped frame rate leaves the CPU to
    the rig. What is drawn is unchanged, only how often. The wait is a timer *before* the frame is
    requested: a requested frame makes Chromium produce one at the next vsync, so requesting it
    first and waiting inside it would keep the compositor at 60 Hz. cancelAnimationFrame is
    wrapped to match."""
    if not max_fps > 0:
        raise ValueError(f"max_fps must be positive, got {max_fps}")
    period_ms = 1000.0 / max_fps
    return (
        "(() => { const raf = window.requestAnimationFrame.bind(window), caf = window.cancelAnimationFrame.bind(window);"
        " let last = 0, next = 1; const live = new Map();"
        " window.requestAnimationFrame = (cb) => { const id = next++;"
        f" const wait = Math.max(0, last + {period_ms:.1f} - performance.now());"
        " live.set(id, { timer: setTimeout(() => { live.set(id, { frame: raf((t) => {"
        " live.delete(id); last = performance.now(); cb(t); }) }); }, wait) }); return id; };"
        " window.cancelAnimationFrame = (id) => { const h = live.get(id); if (!h) return; live.delete(id);"
        " if (h.timer !== undefined) clearTimeout(h.timer); if (h.frame !== undefined) caf(h.frame); }; })();"
    )


def color_mask(img: np.ndarray, rgb: tuple[int, int, int] | np.ndarray, tol: int = 40) -> np.ndarray:
    """`(H, W)` bool: the pixels of `img (H, W, 3)` within `tol` of `rgb` in every channel."""
    return np.all(np.abs(img.astype(int) - np.asarray(rgb, dtype=int)) <= tol, axis=2)


def count_color(img: np.ndarray, rgb: tuple[int, int, int] | np.ndarray, tol: int = 40) -> int:
    """Pixels of `img (H, W, 3)` within `tol` of `rgb` in every channel."""
    return int(color_mask(img, rgb, tol).sum())


def changed_pixels(a: np.ndarray, b: np.ndarray, tol: int = 40) -> int:
    """Pixels where two `(H, W, 3)` images differ by more than `tol` in some channel."""
    return int(np.any(np.abs(a.astype(int) - b.astype(int)) > tol, axis=2).sum())
