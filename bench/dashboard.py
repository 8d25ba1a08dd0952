"""Does the dashboard keep up with a live rig, without its memory growing?

    python -m bagit.bench.dashboard [--seconds 600] [--no-browser] [--json]

Feeds an in-process Dashboard (its render thread on) at the rig's rates for `--seconds`
(default 600; `run(quick=True)` does 20): SOI at 30 Hz, clouds of 20000 coloured points at 10 Hz,
both arms' states at 30 Hz each, controller status and commands at 30 Hz. A headless Chromium
(Debian's, via Playwright) stays connected the whole time, so the server really sends every update
to a browser. Reports:

- RSS of this process (dashboard + feeders; the browser is another process) after warm-up, at
  the end, and its slope over the second half of the run (MB/min; ~0 means no growth);
- the browser's JS heap at the start and end, when Chromium reports it;
- the time an `on_*` call takes (what a Zenoh callback pays), and the update latency per layer:
  from the `on_*` call to the scene update handed to viser's websocket (min / median / p95 / max),
  which includes waiting for the layer's rate limit;
- how many messages were coalesced (latest wins) and any render errors.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bagit.bench.common import stats_ms

QUICK_SECONDS = 20.0
WARMUP_S = 5.0
CLOUD_POINTS = 20000


def rss_mb() -> float:
    """Resident set size of this process (MB), from /proc."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


class _Feeder(threading.Thread):
    """Calls `make(i)` then `deliver(msg)` every 1/hz seconds on a fixed schedule, timing `deliver`."""

    def __init__(self, name: str, hz: float, make: Callable[[int], Any], deliver: Callable[[Any], None], stop: threading.Event,
                 duration_s: float):
        super().__init__(name=f"feed-{name}", daemon=True)
        self.hz, self.make, self.deliver, self.stop_event = hz, make, deliver, stop
        # preallocated, so the benchmark's own bookkeeping does not show up as growth
        self.call_ms = np.zeros(int(hz * (duration_s + 10)) + 16)
        self.sent = 0
        self.late = 0
        self.t_first = self.t_last = 0.0

    def run(self) -> None:
        period = 1.0 / self.hz
        t_next = self.t_first = time.monotonic()
        i = 0
        while not self.stop_event.is_set():
            msg = self.make(i)
            t0 = time.perf_counter()
            self.deliver(msg)
            if i < len(self.call_ms):
                self.call_ms[i] = (time.perf_counter() - t0) * 1e3
            self.sent += 1
            self.t_last = time.monotonic()
            i += 1
            t_next += period
            wait = t_next - time.monotonic()
            if wait > 0:
                self.stop_event.wait(wait)
            else:
                self.late += 1
                if wait < -1.0:  # far behind (a stalled machine): resynchronise rather than burst
                    t_next = time.monotonic()


def run(quick: bool = False, seconds: float | None = None, browser: bool = True) -> dict[str, Any]:
    from bagit.common.messages import Command, ControllerStatus, PointCloud, RunControlReply, SoiState
    from bagit.dashboard import Dashboard, DashboardConfig
    from bagit.dashboard.browser import BrowserPage, chromium_available
    from bagit.services.planner import plan

    duration = QUICK_SECONDS if quick and seconds is None else (seconds or 600.0)
    if duration <= WARMUP_S:
        raise ValueError(f"--seconds must be more than the {WARMUP_S:g} s warm-up, got {duration}")

    class _Link:  # nobody presses buttons in this benchmark
        def start(self, scenario: Any, params: Any, controller: str | None = None) -> RunControlReply:
            return RunControlReply(accepted=False, reason="benchmark")

        def stop(self) -> RunControlReply:
            return RunControlReply(accepted=False, reason="benchmark")

        reset = stop

        def estop(self, reason: str) -> None:
            pass

        def release_estop(self, reason: str) -> None:
            pass

    r = plan("exp01", seed=0)
    rim0 = r.path[0]
    rng = np.random.default_rng(0)
    base_cloud = rim0.mean(axis=0) + rng.normal(scale=[0.06, 0.06, 0.08], size=(CLOUD_POINTS, 3))
    colors = rng.integers(0, 255, (CLOUD_POINTS, 3), dtype=np.uint8)
    noise = rng.normal(scale=0.002, size=(64, CLOUD_POINTS, 3)).astype(np.float32)

    from bagit.common import cr5
    from bagit.common.geometry import matrix_to_rpy
    from bagit.common.messages import ArmState
    from bagit.common.rig import ArmName, RigConfig

    rig = RigConfig()
    q_home = np.radians([0.0, -20.0, -100.0, 30.0, 90.0, 0.0])

    def arm_msg(arm: ArmName, i: int) -> ArmState:
        q = q_home + 0.2 * np.sin(i / 30 + np.arange(6))
        T = rig.arms[arm].T_world_base() @ cr5.fk(q)
        return ArmState(arm=arm, q=q, qd=np.full(6, 0.05), tool_pose=np.r_[T[:3, 3], matrix_to_rpy(T[:3, :3])])

    dash = Dashboard(_Link(), DashboardConfig(port=0, max_cloud_points=CLOUD_POINTS, draw_without_viewers=True))
    page = None
    try:
        if r.goal is None:
            raise RuntimeError("the exp01 plan has no goal")
        dash.on_goal(r.goal.to_message("bench", 0.15))
        dash.on_path(r.to_message("bench"))
        if browser and chromium_available():
            page = BrowserPage(dash.url)
            page.wait_text("Stage:")
        stop = threading.Event()
        feeders = [
            _Feeder("soi", 30, lambda i: SoiState(seq=i, rim=rim0 + 0.01 * np.sin(i / 15)), dash.on_soi, stop, duration),
            _Feeder("cloud", 10, lambda i: PointCloud(seq=i, points=(base_cloud + noise[i % 64]).astype(np.float32), colors=colors),
                    dash.on_cloud, stop, duration),
            _Feeder("arm-left", 30, lambda i: arm_msg("left", i), dash.on_arm_state, stop, duration),
            _Feeder("arm-right", 30, lambda i: arm_msg("right", i), dash.on_arm_state, stop, duration),
            _Feeder("status", 30, lambda i: ControllerStatus(run_id="bench", seq=i, subgoal_index=i // 30 % len(r.path),
                                                             error_to_subgoal=0.01, error_to_goal=0.02, solve_ms=3.0),
                    dash.on_controller_status, stop, duration),
            _Feeder("cmd", 30, lambda i: Command(run_id="bench", seq=i, u=np.full(12, 1e-4)), dash.on_command, stop, duration),
        ]
        t_start = time.monotonic()
        for f in feeders:
            f.start()
        rss: list[tuple[float, float]] = []
        heap_start = heap_end = None
        while (elapsed := time.monotonic() - t_start) < duration:
            rss.append((elapsed, rss_mb()))
            if heap_start is None and elapsed >= WARMUP_S and page is not None:
                heap_start = page.js_heap_mb()
            time.sleep(1.0)
        if page is not None:
            heap_end = page.js_heap_mb()
        stop.set()
        for f in feeders:
            f.join(5.0)
        stats = dash.stats()
        browser_errors = list(page.errors) if page is not None else None
    finally:
        if page is not None:
            page.close()
        dash.close()

    t = np.array([x[0] for x in rss])
    m = np.array([x[1] for x in rss])
    after = t >= WARMUP_S
    half = t >= max(WARMUP_S, duration / 2)
    slope = float(np.polyfit(t[half] / 60.0, m[half], 1)[0]) if half.sum() >= 3 else float("nan")
    latency = {k: v for k, v in stats["latency"].items()}
    return {
        "seconds": duration,
        "browser": page is not None,
        "browser_errors": browser_errors,
        "rates_hz": {f.name.removeprefix("feed-"): (f.sent - 1) / max(f.t_last - f.t_first, 1e-9) for f in feeders},
        "feeder_late_ticks": {f.name.removeprefix("feed-"): f.late for f in feeders},
        "rss_mb": {
            "after_warmup": float(m[after][0]) if after.any() else float(m[0]),
            "end": float(m[-1]),
            "max": float(m.max()),
            "growth_after_warmup": float(m[-1] - (m[after][0] if after.any() else m[0])),
            "slope_second_half_mb_per_min": slope,
        },
        "js_heap_mb": {"start": heap_start, "end": heap_end},
        "on_call_ms": {f.name.removeprefix("feed-"): stats_ms(f.call_ms[: min(f.sent, len(f.call_ms))]) for f in feeders},
        "update_latency_ms": latency,
        "coalesced": {k: v["coalesced"] for k, v in stats["slots"].items()},
        "drawn": {k: v["taken"] for k, v in stats["slots"].items()},
        "render_errors": stats["render_errors"],
    }


def _print_human(res: dict[str, Any]) -> None:
    print(f"dashboard under load for {res['seconds']:.0f} s, browser connected: {res['browser']}")
    print("  fed (Hz): " + ", ".join(f"{k} {v:.1f}" for k, v in res["rates_hz"].items()))
    r = res["rss_mb"]
    print(f"  RSS: {r['after_warmup']:.1f} MB after warm-up -> {r['end']:.1f} MB at the end (max {r['max']:.1f}); "
          f"growth {r['growth_after_warmup']:+.1f} MB, slope over the second half {r['slope_second_half_mb_per_min']:+.2f} MB/min")
    h = res["js_heap_mb"]
    if h["start"] is not None:
        print(f"  browser JS heap: {h['start']:.1f} MB -> {h['end']:.1f} MB")
    print("  on_* call (ms):        " + ", ".join(f"{k} med {v['median_ms']:.3f} p95 {v['p95_ms']:.3f}"
                                                  for k, v in res["on_call_ms"].items() if v.get("n")))
    print("  update latency (ms):   on_* call -> handed to the websocket (includes the rate-limit wait)")
    for k, v in sorted(res["update_latency_ms"].items()):
        if v.get("n"):
            print(f"    {k:14s} n {v['n']:6d}  min {v['min_ms']:7.2f}  median {v['median_ms']:7.2f}  p95 {v['p95_ms']:7.2f}  max {v['max_ms']:8.2f}")
    print("  drawn / coalesced: " + ", ".join(f"{k} {res['drawn'][k]}/{res['coalesced'][k]}" for k in sorted(res["drawn"])))
    if res["render_errors"]:
        print(f"  render errors: {res['render_errors']}")
    if res["browser_errors"]:
        print(f"  browser errors: {res['browser_errors'][:5]}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bagit.bench.dashboard", description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="how long to feed (default 600)")
    ap.add_argument("--quick", action="store_true", help=f"{QUICK_SECONDS:g} s")
    ap.add_argument("--no-browser", action="store_true", help="no headless Chromium attached")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    res = run(quick=a.quick, seconds=None if a.quick else a.seconds, browser=not a.no_browser)
    if a.json:
        print(json.dumps(res))
    else:
        _print_human(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
