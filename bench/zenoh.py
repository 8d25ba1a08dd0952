"""The Zenoh transport on loopback: latency and throughput of the messages that matter most.

    python -m bagit.bench.zenoh [--quick]

- SOI messages (n_x = 64 rim points) at 30 Hz: one-way latency, encode to decoded callback.
- RGB-D frames at 640x480 (uint8 colour + uint16 depth, ~1.5 MB) at 30 Hz: delivered rate,
  drops and latency; the goal is 30 frames/s with no drops and p99 <= 30 ms on 2 cores.
- The same SOI latency while frames stream (what perception -> controller sees on a busy rig).
- Frames unthrottled: the most frames/s the transport delivers.

Each is measured between two sessions in one process (linked over loopback TCP) and between two
processes (the subscriber is a child `python -m bagit.bench.zenoh --role sub`). Latency uses the
message's own `stamp` (time.time() just before the put) against time.time() after decoding: one
clock, so one-way times are exact on one machine.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np

from bagit.bench.common import stats_ms
from bagit.common.bus import BusConfig, Keys, Publisher, Subscriber, locators, open_session
from bagit.common.messages import Message, RgbdFrame, SoiState

RIG = "bench"
H, W = 480, 640


def _frame(seq: int, color: np.ndarray, depth: np.ndarray) -> RgbdFrame:
    return RgbdFrame(seq=seq, color=color, depth=depth)


def _images(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 255, (H, W, 3), dtype=np.uint8), rng.integers(300, 3000, (H, W), dtype=np.uint16)


def _soi(seq: int, rim: np.ndarray) -> SoiState:
    return SoiState(seq=seq, rim=rim, source_stamp=time.time())


def _stats(lat_ms: list[float]) -> dict[str, float]:
    """min / median / p95 / mean (as every bench reports) plus p99 and max, in ms."""
    a = np.asarray(lat_ms, dtype=float)
    out = stats_ms(a)
    if a.size:
        out.update(p99_ms=float(np.percentile(a, 99)), max_ms=float(a.max()))
    return out


class _Collector:
    """Receive-side bookkeeping: latency per message and the last seq, thread-safe."""

    def __init__(self) -> None:
        self.lat_ms: list[float] = []
        self.seqs: list[int] = []
        self.last = time.monotonic()
        self.lock = threading.Lock()

    def __call__(self, m: Message) -> None:
        now = time.time()
        with self.lock:
            self.lat_ms.append((now - m.stamp) * 1e3)
            self.seqs.append(int(getattr(m, "seq", 0)))
            self.last = time.monotonic()

    def snapshot(self) -> tuple[list[float], list[int]]:
        with self.lock:
            return list(self.lat_ms), list(self.seqs)


def _publish(pub: Publisher, make, count: int, rate_hz: float | None, t_end_budget: float) -> tuple[int, float]:
    """Put `count` messages at `rate_hz` (None: as fast as possible); returns (sent, seconds)."""
    t0 = time.perf_counter()
    period = 1.0 / rate_hz if rate_hz else 0.0
    sent = 0
    for i in range(count):
        if period:
            target = t0 + i * period
            delay = target - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        pub.put(make(i))
        sent += 1
        if time.perf_counter() - t0 > t_end_budget:
            break
    return sent, time.perf_counter() - t0


def _wait_quiet(col: _Collector, expected: int, idle_s: float = 1.0, cap_s: float = 10.0) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < cap_s:
        lat, _ = col.snapshot()
        if len(lat) >= expected or time.monotonic() - col.last > idle_s:
            return
        time.sleep(0.02)


# --------------------------------------------------------------------------------------------
# The subscriber child process
# --------------------------------------------------------------------------------------------


def _child(args: argparse.Namespace) -> int:
    s = open_session(BusConfig(rig=RIG, connect=[args.connect]))
    keys = Keys(RIG)
    cols = {"rgbd": _Collector(), "soi": _Collector()}
    subs: list[Subscriber[Any]] = [Subscriber(s, keys.camera_rgbd, RgbdFrame, cols["rgbd"]), Subscriber(s, keys.perception_soi, SoiState, cols["soi"])]
    print("ready", flush=True)
    # the parent says when it is done sending by closing our stdin
    sys.stdin.read()
    time.sleep(0.5)
    out: dict[str, Any] = {}
    for k, c in cols.items():
        lat, seqs = c.snapshot()
        out[k] = {"lat_ms": lat, "seqs": seqs}
    out["dropped"] = sum(x.dropped for x in subs)
    for x in subs:
        x.close()
    s.close()
    print(json.dumps(out), flush=True)
    return 0


class _Remote:
    """A subscriber child process; `results()` ends it and returns what it received."""

    def __init__(self, endpoint: str) -> None:
        self.p = subprocess.Popen(
            [sys.executable, "-m", "bagit.bench.zenoh", "--role", "sub", "--connect", endpoint],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )
        if self.p.stdout is None:  # (stdout=PIPE)
            raise RuntimeError("benchmark child has no stdout pipe")
        line = self.p.stdout.readline().strip()
        if line != "ready":
            self.p.kill()
            raise RuntimeError(f"benchmark child did not start: {line!r}")

    def results(self) -> dict[str, Any]:
        out, _ = self.p.communicate(input="", timeout=60)
        return json.loads(out.strip().splitlines()[-1])

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(5)


# --------------------------------------------------------------------------------------------
# Scenarios
# --------------------------------------------------------------------------------------------


def _scenario(where: str, seconds: float, frames_hz: float | None, soi_hz: float | None) -> dict[str, Any]:
    """One measurement: frames at `frames_hz` (None: off, 0: unthrottled) and/or SOI at `soi_hz`."""
    keys = Keys(RIG)
    a = open_session(BusConfig(rig=RIG, adminspace=True))
    b = None
    remote: _Remote | None = None
    try:
        endpoint = locators(a)[0]
        cols = {"rgbd": _Collector(), "soi": _Collector()}
        subs: list[Subscriber] = []
        if where == "in-process":
            b = open_session(BusConfig(rig=RIG, connect=[endpoint]))
            subs = [Subscriber(b, keys.camera_rgbd, RgbdFrame, cols["rgbd"]), Subscriber(b, keys.perception_soi, SoiState, cols["soi"])]
        else:
            remote = _Remote(endpoint)
        cam = Publisher(a, keys.camera_rgbd, RgbdFrame)
        soi = Publisher(a, keys.perception_soi, SoiState)
        t_wait = time.monotonic()
        while not (cam.matched and soi.matched) and time.monotonic() - t_wait < 10:
            time.sleep(0.01)
        color, depth = _images()
        rim = np.random.default_rng(1).normal(size=(64, 3))
        sent: dict[str, int] = {}
        dur: dict[str, float] = {}
        threads = []
        if frames_hz is not None:
            n = int(seconds * (frames_hz or 1000))

            def run_frames():
                sent["rgbd"], dur["rgbd"] = _publish(cam, lambda i: _frame(i, color, depth), n, frames_hz or None, seconds)

            threads.append(threading.Thread(target=run_frames))
        if soi_hz is not None:
            n_soi = int(seconds * soi_hz)

            def run_soi():
                sent["soi"], dur["soi"] = _publish(soi, lambda i: _soi(i, rim), n_soi, soi_hz, seconds)

            threads.append(threading.Thread(target=run_soi))
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if remote is not None:
            res = remote.results()
            got = {k: (res[k]["lat_ms"], res[k]["seqs"]) for k in ("rgbd", "soi")}
            dropped_bad = res["dropped"]
        else:
            for k in sent:
                _wait_quiet(cols[k], sent[k])
            got = {k: c.snapshot() for k, c in cols.items()}
            dropped_bad = sum(s.dropped for s in subs)
        out: dict[str, Any] = {"where": where, "seconds": seconds, "malformed": dropped_bad}
        for k in sent:
            lat, seqs = got[k]
            recv = len(seqs)
            span = dur[k] if dur[k] > 0 else float("nan")
            out[k] = {
                "sent": sent[k],
                "received": recv,
                "lost": sent[k] - len(set(seqs)),
                "sent_per_s": sent[k] / span,
                "received_per_s": recv / span,
                "mb_per_s": (recv * (H * W * 5) / 1e6 / span) if k == "rgbd" else None,
                "latency": _stats(lat),
            }
        return out
    finally:
        if remote is not None:
            remote.kill()
        if b is not None:
            b.close()
        a.close()


def run(quick: bool = False) -> dict[str, Any]:
    """All the measurements; `quick` shortens each to ~2 s."""
    secs = 2.0 if quick else 8.0
    res: dict[str, Any] = {}
    for where in ("in-process", "cross-process"):
        res[f"soi_30hz_{where}"] = _scenario(where, secs, None, 30.0)
        res[f"rgbd_30hz_{where}"] = _scenario(where, secs, 30.0, None)
        res[f"soi_under_rgbd_30hz_{where}"] = _scenario(where, secs, 30.0, 30.0)
        res[f"rgbd_max_{where}"] = _scenario(where, min(secs, 3.0), 0.0, None)
    goal = res["rgbd_30hz_cross-process"]["rgbd"]
    res["goal_30fps_no_drops_p99_le_30ms"] = bool(
        goal["lost"] == 0 and goal["received_per_s"] >= 29.0 and goal["latency"].get("p99_ms", 1e9) <= 30.0
    )
    return res


def _print(res: dict[str, Any]) -> None:
    print(f"{'scenario':<34} {'key':<5} {'sent':>5} {'recv':>5} {'lost':>4} {'recv/s':>7} {'min':>7} {'p50':>7} {'p95':>7} {'p99':>7} ms")
    for name, r in res.items():
        if not isinstance(r, dict):
            continue
        for k in ("rgbd", "soi"):
            if k in r:
                x, lat = r[k], r[k]["latency"]
                print(
                    f"{name:<34} {k:<5} {x['sent']:>5} {x['received']:>5} {x['lost']:>4} {x['received_per_s']:>7.1f} "
                    f"{lat.get('min_ms', float('nan')):>7.2f} {lat.get('median_ms', float('nan')):>7.2f} "
                    f"{lat.get('p95_ms', float('nan')):>7.2f} {lat.get('p99_ms', float('nan')):>7.2f}"
                )
    print(f"goal (30 frames/s cross-process, no drops, p99 <= 30 ms): {'met' if res['goal_30fps_no_drops_p99_le_30ms'] else 'NOT met'}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bagit.bench.zenoh", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="~2 s per measurement instead of ~8 s")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.add_argument("--role", choices=["main", "sub"], default="main", help=argparse.SUPPRESS)
    p.add_argument("--connect", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.role == "sub":
        return _child(args)
    res = run(quick=args.quick)
    print(json.dumps(res, indent=1)) if args.json else _print(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
